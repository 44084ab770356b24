"""A perfect acoustic link on the v1 ids: the overrides that make one (a fix every control step,
no latency, loss or noise) and the observation such an env would show, built from the present
true target in ``info``. Used by the control floor and by privileged teachers in training."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from auv_follow_env.layout import OBS_INDEX_V1

__all__ = ["perfect_link_overrides", "perfect_link_observation"]

_I = OBS_INDEX_V1


def perfect_link_overrides(dt: float = 0.05) -> dict[str, object]:
    """The v1 overrides of a perfect link: a fix every control step ``dt``, zero latency, no
    loss, no fix noise. :func:`perfect_link_observation` gives a controller what an env made
    with these overrides would show it (equal when the link draws no random numbers; tested)."""
    return {"update_period_s": float(dt), "period_jitter_s": 0.0, "latency_model": "constant", "latency_s": 0.0,
            "latency_spread_s": 0.0, "loss_prob": 0.0, "burst_p_good_bad": 0.0, "fix_sigma_m": 0.0,
            "fix_sigma_per_m": 0.0, "heading_sigma_rad": 0.0, "velocity_sigma_mps": 0.0,
            "yaw_rate_sigma_radps": 0.0}


def perfect_link_observation(obs: np.ndarray, true_target: np.ndarray, follower_pose: np.ndarray,
                             p_d: Sequence[float]) -> np.ndarray:
    """v1 observations (N, 20) with the target fields replaced by the present, exact target.

    Args:
        obs: the env's observations (N, 20) (fields 0-4 and 14-15 are kept: the follower's own
            velocity, heading and the measured current).
        true_target: (N, 6) present target x, y, psi, u, v, r (``info["true_target"]``).
        follower_pose: (N, 3) follower x, y, psi (``info["follower_pose"]``).
        p_d: reference offset in the target frame [m].

    Returns:
        float32 (N, 20): fields 5-13 as eq. (21) with the present target, ``packet_age`` =
        ``since_arrival`` = 0, ``new_packet`` = ``has_packet`` = 1.
    """
    o = np.asarray(obs)
    if o.ndim != 2 or o.shape[1] != len(_I):
        raise ValueError(f"obs has shape {o.shape}: must be (N, {len(_I)}) v1 observations")
    tt = np.asarray(true_target, dtype=np.float64)
    fp = np.asarray(follower_pose, dtype=np.float64)
    out = o.astype(np.float64)
    x, y, ps = fp[:, 0], fp[:, 1], fp[:, 2]
    xt, yt, pt = tt[:, 0], tt[:, 1], tt[:, 2]
    c, s = np.cos(ps), np.sin(ps)
    ct, st = np.cos(pt), np.sin(pt)
    pdx, pdy = float(p_d[0]), float(p_d[1])
    ex, ey = xt - x, yt - y
    rx, ry = xt + ct * pdx - st * pdy - x, yt + st * pdx + ct * pdy - y
    out[:, _I["target_dx"]] = c * ex + s * ey
    out[:, _I["target_dy"]] = -s * ex + c * ey
    out[:, _I["target_cos_dpsi"]] = np.cos(pt - ps)
    out[:, _I["target_sin_dpsi"]] = np.sin(pt - ps)
    out[:, _I["target_u"]] = tt[:, 3]
    out[:, _I["target_v"]] = tt[:, 4]
    out[:, _I["target_r"]] = tt[:, 5]
    out[:, _I["ref_dx"]] = c * rx + s * ry
    out[:, _I["ref_dy"]] = -s * rx + c * ry
    out[:, _I["packet_age"]] = 0.0
    out[:, _I["since_arrival"]] = 0.0
    out[:, _I["new_packet"]] = 1.0
    out[:, _I["has_packet"]] = 1.0
    return out.astype(np.float32)
