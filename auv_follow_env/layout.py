"""The observation layout, defined once and decoded by name.

Everything is in the follower's body frame (x forward, y to port as in eq. (3)), in SI
units, and of order 0.1-1 in normal operation, so a learning agent needs no rescaling.
The follower never sees the true present target: only the target state ``tau`` seconds
old, as eq. (12) says.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

__all__ = ["ObsField", "OBS_FIELDS", "OBS_INDEX", "OBS_DIM", "decode", "obs_slice"]


@dataclass(frozen=True)
class ObsField:
    name: str
    unit: str
    description: str


OBS_FIELDS: tuple[ObsField, ...] = (
    ObsField("u", "m/s", "follower surge velocity (ground-referenced)"),
    ObsField("v", "m/s", "follower sway velocity (ground-referenced)"),
    ObsField("r", "rad/s", "follower yaw rate"),
    ObsField("cos_psi", "-", "cosine of the follower heading (compass)"),
    ObsField("sin_psi", "-", "sine of the follower heading (compass)"),
    ObsField("target_dx", "m", "delayed target position minus follower position, body x"),
    ObsField("target_dy", "m", "delayed target position minus follower position, body y"),
    ObsField("target_cos_dpsi", "-", "cosine of (delayed target heading - follower heading)"),
    ObsField("target_sin_dpsi", "-", "sine of (delayed target heading - follower heading)"),
    ObsField("target_u", "m/s", "delayed target surge velocity (target body frame)"),
    ObsField("target_v", "m/s", "delayed target sway velocity (target body frame)"),
    ObsField("target_r", "rad/s", "delayed target yaw rate"),
    ObsField("ref_dx", "m", "delayed reference point p_t(t-tau) + R p_d minus follower, body x"),
    ObsField("ref_dy", "m", "delayed reference point p_t(t-tau) + R p_d minus follower, body y"),
    ObsField("current_u", "m/s", "measured current, body x (u_c of eq. (5))"),
    ObsField("current_v", "m/s", "measured current, body y (v_c of eq. (5))"),
)

OBS_INDEX = MappingProxyType({f.name: i for i, f in enumerate(OBS_FIELDS)})
OBS_DIM = len(OBS_FIELDS)


def obs_slice(first: str, last: str) -> slice:
    """The slice from field ``first`` to field ``last`` inclusive."""
    return slice(OBS_INDEX[first], OBS_INDEX[last] + 1)


def decode(obs: np.ndarray) -> dict[str, np.ndarray]:
    """Split observations (shape (..., OBS_DIM)) into named float64 arrays of shape (...).

    Raises:
        ValueError: if the last axis is not OBS_DIM long.
    """
    a = np.asarray(obs, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != OBS_DIM:
        raise ValueError(f"observation of shape {a.shape} does not match the layout: "
                         f"the last axis must have {OBS_DIM} entries")
    return {f.name: a[..., i] for i, f in enumerate(OBS_FIELDS)}
