"""Shared machinery of the scripted controllers: the SB3 ``predict`` protocol over a batch,
per-env memory reset on ``episode_start``, and filtered differentiation."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from auv_follow_env.layout import LAYOUTS, OBS_DIM, OBS_DIM_V1, OBS_INDEX_V1
from auv_follow_env.params import TaskSpec

__all__ = ["ScriptedPolicy", "ObservationHold", "check_real", "as_batch", "as_mask", "FilteredDerivative", "wrap_to_pi",
           "sat"]


def check_real(name: str, value: Any, lo: float, strict: bool) -> None:
    """A ValueError naming ``name`` unless ``value`` is a finite real number (Python or numpy, not a
    bool) above ``lo`` (``strict``) or at least ``lo``."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if ok:
        try:
            x = float(value)
        except OverflowError:
            ok = False
        else:
            ok = math.isfinite(x) and (x > lo if strict else x >= lo)
    if not ok:
        raise ValueError(f"{name}={value!r} is invalid: must be a finite number {'>' if strict else '>='} {lo:g}")


def wrap_to_pi(a: np.ndarray) -> np.ndarray:
    """Angle wrapped into (-pi, pi] (eq. (24))."""
    return np.arctan2(np.sin(a), np.cos(a))


def sat(z: np.ndarray) -> np.ndarray:
    """Boundary-layer saturation, eq. (35): clip to [-1, 1]."""
    return np.clip(z, -1.0, 1.0)


@njit(cache=True)
def _to_actions(forces, limits, out):
    """out = np.clip(forces / limits, -1, 1).astype(np.float32), in one pass (same operations)."""
    for i in range(forces.shape[0]):
        for j in range(forces.shape[1]):
            z = forces[i, j] / limits[j]
            if z < -1.0:
                z = -1.0
            elif z > 1.0:
                z = 1.0
            out[i, j] = np.float32(z)


class FilteredDerivative:
    """Batched filtered differentiation D(s) = s / (T_f s + 1), Tustin-discretised at dt.

    ``d_k = (2 (x_k - x_{k-1}) + (2 T_f - dt) d_{k-1}) / (2 T_f + dt)``; at an env's first
    sample after a reset the derivative is 0.
    """

    def __init__(self, dt: float, time_constant: float) -> None:
        if not (math.isfinite(time_constant) and time_constant >= 0):
            raise ValueError(f"time_constant={time_constant!r} is invalid: must be a finite number >= 0 [s]")
        self.a = 2.0 / (2.0 * time_constant + dt)
        self.b = (2.0 * time_constant - dt) / (2.0 * time_constant + dt)
        self.prev: np.ndarray | None = None
        self.d: np.ndarray | None = None

    def reset(self, mask: np.ndarray, x: np.ndarray) -> None:
        """Restart the envs where ``mask`` is set at the current sample ``x``."""
        if self.prev is None or self.prev.shape != x.shape:
            self.prev = x.copy()
            self.d = np.zeros_like(x)
            return
        self.prev[mask] = x[mask]
        self.d[mask] = 0.0

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.d = self.a * (x - self.prev) + self.b * self.d
        self.prev = x.copy()
        return self.d


def as_batch(observation: Any, widths: tuple[int, ...]) -> tuple[np.ndarray, bool]:
    """(observations as a float64 (N, W) array, whether one (W,) observation was given).

    Raises:
        ValueError: not 1-D or 2-D, or a width W not in ``widths``.
    """
    obs = np.asarray(observation, dtype=np.float64)
    single = obs.ndim == 1
    if single:
        obs = obs[None, :]
    if obs.ndim != 2 or obs.shape[1] not in widths:
        raise ValueError(f"observation has shape {np.shape(observation)}: expected (W,) or (N, W) "
                         f"with W = {' or '.join(str(w) for w in widths)}")
    return obs, single


def as_mask(mask: Any, n: int, name: str) -> np.ndarray:
    """A per-env bool mask of shape (n,) (all False for None), or a ValueError naming ``name``."""
    if mask is None:
        return np.zeros(n, dtype=bool)
    m = np.asarray(mask, dtype=bool).reshape(-1)
    if m.shape != (n,):
        raise ValueError(f"{name} has shape {np.shape(mask)}: expected ({n},)")
    return m


#: v1 columns of the newest packet (target and reference fields, its two ages)
_PACKET = np.r_[OBS_INDEX_V1["target_dx"]:OBS_INDEX_V1["ref_dy"] + 1,
                OBS_INDEX_V1["packet_age"], OBS_INDEX_V1["since_arrival"]]
_AGES = np.array([OBS_INDEX_V1["packet_age"], OBS_INDEX_V1["since_arrival"]])
_NEW, _HAS = OBS_INDEX_V1["new_packet"], OBS_INDEX_V1["has_packet"]
HOLD_DOC = "docs/api.md#non-finite-observations"


def _names(width: int, bad_row: np.ndarray) -> str:
    return ", ".join(f.name for f, b in zip(LAYOUTS[width], bad_row, strict=True) if b)


class ObservationHold:
    """The recovery rule for observations with a non-finite field (NaN or +-inf), per env.

    A field that is not finite takes its last finite value of the episode. On the v1 layout
    a non-finite field of the newest packet (fields 5-13, ``packet_age``, ``since_arrival``)
    or of ``new_packet`` drops that step's packet: every packet field keeps the last packet's
    value, its two ages grow by ``dt`` (while a packet is held), and ``new_packet`` is 0. The
    next finite observation is used as it is: nothing non-finite outlives its step.

    An episode's first observation has nothing to hold: a non-finite field there raises a
    ValueError naming the row and the fields. :attr:`held` counts the (env, step) pairs that
    held a field; the first hold of an instance issues one ``RuntimeWarning``.

    Call it with the batch (N, W) float64 and the per-env episode-start mask; ``commit=False``
    applies the rule without remembering the observation (a peek).
    """

    def __init__(self, dt: float) -> None:
        self.dt = float(dt)
        self._last: np.ndarray | None = None
        self.held = 0
        self._warned = False

    def reset(self) -> None:
        """Forget every env: the next call is each env's first observation."""
        self._last = None

    def __call__(self, obs: np.ndarray, start: np.ndarray | None = None, commit: bool = True) -> np.ndarray:
        fresh = self._last is None or self._last.shape != obs.shape
        bad = ~np.isfinite(obs)
        if not bad.any():
            if commit:
                if fresh:
                    self._last = obs.copy()
                else:
                    np.copyto(self._last, obs)
            return obs
        rows = bad.any(axis=1)
        first = np.ones(obs.shape[0], dtype=bool) if fresh else (
            np.zeros(obs.shape[0], dtype=bool) if start is None else np.asarray(start, dtype=bool))
        if np.any(rows & first):
            i = int(np.flatnonzero(rows & first)[0])
            raise ValueError(f"observation row {i} has non-finite {_names(obs.shape[1], bad[i])} "
                             f"({', '.join(repr(float(obs[i, j])) for j in np.flatnonzero(bad[i]))}) at the first "
                             f"step of its episode: there is no earlier value to hold ({HOLD_DOC})")
        last = self._last
        out = np.where(bad, last, obs)
        if obs.shape[1] == OBS_DIM_V1:
            drop = bad[:, _PACKET].any(axis=1) | bad[:, _NEW]
            if drop.any():
                out[np.ix_(drop, _PACKET)] = last[np.ix_(drop, _PACKET)]
                ages = last[np.ix_(drop, _AGES)] + self.dt * (last[drop, _HAS] > 0)[:, None]
                out[np.ix_(drop, _AGES)] = ages
                out[drop, _NEW] = 0.0
        self.held += int(rows.sum())
        if not self._warned:
            import warnings

            self._warned = True
            i = int(np.flatnonzero(rows)[0])
            warnings.warn(f"observation row {i} has non-finite {_names(obs.shape[1], bad[i])}: held at the last "
                          f"finite values ({HOLD_DOC}; warned once per controller)", RuntimeWarning, stacklevel=3)
        if commit:
            np.copyto(last, out)
        return out


class ScriptedPolicy:
    """Base of the scripted controllers: an SB3-style policy over observations.

    Subclasses implement :meth:`forces` (batched, (N, W) -> (N, 3) in N / N m),
    :meth:`reference` (the reference point they generate, in the follower body frame) and
    :meth:`_reset_memory` (per-env memory where a mask is set).

    ``predict`` accepts one observation or a batch (N, width) of either layout (width 16
    for v0, 20 for v1; :mod:`auv_follow_env.layout`). Memory is reset
    where ``episode_start`` is True; if ``episode_start`` is None, call :meth:`reset`
    at each new episode yourself (the first call always starts fresh). A non-finite
    observation field is held at its last finite value (:class:`ObservationHold`).
    """

    name = "scripted"
    obs_dims: tuple[int, ...] = (OBS_DIM, OBS_DIM_V1)  #: observation widths this policy reads

    def __init__(self, spec: TaskSpec) -> None:
        if not isinstance(spec, TaskSpec):
            raise TypeError(f"spec must be an auv_follow_env TaskSpec, got {type(spec).__name__}; "
                            f"use env.unwrapped.task_spec or auv_follow_env.make_task_spec(...)")
        self.spec = spec
        self.dt = spec.dt
        self._limits = np.asarray(spec.force_limits, dtype=np.float64)
        self._n: int | None = None
        self.last_forces: np.ndarray | None = None
        #: the recovery rule for non-finite observation fields (:class:`ObservationHold`)
        self.hold = ObservationHold(spec.dt)

    def reset(self) -> None:
        """Forget all memory: the next call starts fresh for every env."""
        self._n = None
        self.hold.reset()

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        obs, single = as_batch(observation, self.obs_dims)
        n = obs.shape[0]
        if self._n != n:
            mask = np.ones(n, dtype=bool)
            self._n = n
        else:
            mask = as_mask(episode_start, n, "episode_start")
        obs = self.hold(obs, mask)
        forces = self.forces(obs, mask)
        self.last_forces = forces
        if (isinstance(forces, np.ndarray) and forces.dtype == np.float64 and forces.ndim == 2
                and forces.shape[1] == self._limits.shape[0]):
            actions = np.empty(forces.shape, dtype=np.float32)
            _to_actions(forces, self._limits, actions)
        else:
            actions = np.clip(forces / self._limits, -1.0, 1.0).astype(np.float32)
        return (actions[0] if single else actions), state

    def __call__(self, observation: Any) -> np.ndarray:
        return self.predict(observation)[0]

    # to implement -------------------------------------------------------------------------
    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def reference(self, observation: Any) -> np.ndarray:  # pragma: no cover
        """The reference (x, y, psi) this controller generates, relative to the follower in its
        body frame, for observations (N, W) -> (N, 3). Does not change the policy's memory."""
        raise NotImplementedError
