"""The observation layouts, defined once and decoded by name.

Everything is in the follower's body frame (x forward, y to port as in eq. (3)), in SI
units, and of order 0.1-1 in normal operation, so a learning agent needs no rescaling.
The follower never sees the true present target.

* **v0** (``AUVFollow-S1-v0`` ... ``-S4-v0``, ``AUVFollow-v0``; :data:`OBS_FIELDS`, 16 fields):
  the target state exactly ``tau`` seconds old, as eq. (12) says.
* **v1** (the acoustic-link tiers ``AUVFollow-*-v1``; :data:`OBS_FIELDS_V1`, 20 fields): the
  same 16 fields, where "delayed target" now means *the newest packet received so far*
  (measured at an earlier send time, possibly noisy), followed by four fields that say how
  stale it is: ``packet_age`` (now minus the packet's measurement time), ``since_arrival``
  (now minus the time that packet arrived), ``new_packet`` (1 on the step a newer packet
  arrived, else 0) and ``has_packet`` (0 until the first packet arrives; while 0, fields
  5-13 and 16-17 are 0). A v0 observation is a v1 observation with ``packet_age = tau``,
  ``since_arrival = 0``, ``new_packet = 1`` and ``has_packet = 1`` on every step.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

__all__ = ["ObsField", "OBS_FIELDS", "OBS_INDEX", "OBS_DIM", "OBS_FIELDS_V1", "OBS_INDEX_V1", "OBS_DIM_V1",
           "LAYOUTS", "decode", "obs_slice"]


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

#: v1: the v0 fields (target fields = newest received packet) and the link's staleness
OBS_FIELDS_V1: tuple[ObsField, ...] = OBS_FIELDS + (
    ObsField("packet_age", "s", "now minus the measurement time of the newest received packet (0 if none)"),
    ObsField("since_arrival", "s", "now minus the arrival time of the newest received packet (0 if none)"),
    ObsField("new_packet", "-", "1 if a newer packet arrived on this step, else 0"),
    ObsField("has_packet", "-", "1 once any packet has arrived this episode, else 0"),
)
OBS_INDEX_V1 = MappingProxyType({f.name: i for i, f in enumerate(OBS_FIELDS_V1)})
OBS_DIM_V1 = len(OBS_FIELDS_V1)

#: observation width -> field tuple (the layout is recognised by its width)
LAYOUTS = MappingProxyType({OBS_DIM: OBS_FIELDS, OBS_DIM_V1: OBS_FIELDS_V1})


def obs_slice(first: str, last: str) -> slice:
    """The slice from field ``first`` to field ``last`` inclusive (either layout)."""
    return slice(OBS_INDEX_V1[first], OBS_INDEX_V1[last] + 1)


def decode(obs: np.ndarray) -> dict[str, np.ndarray]:
    """Split observations (shape (..., 16) for v0 or (..., 20) for v1) into named float64
    arrays of shape (...). The layout is recognised by the width of the last axis.

    Raises:
        ValueError: if the last axis is neither OBS_DIM (16) nor OBS_DIM_V1 (20) long.
    """
    a = np.asarray(obs, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] not in LAYOUTS:
        raise ValueError(f"observation of shape {a.shape} does not match a layout: the last axis must "
                         f"have {OBS_DIM} (v0) or {OBS_DIM_V1} (v1) entries")
    return {f.name: a[..., i] for i, f in enumerate(LAYOUTS[a.shape[-1]])}
