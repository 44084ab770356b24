"""Per-step traces of single episodes: what the report plots (it never loads a model itself)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from agents.benchmark.policies import IncompatiblePolicy, PolicySpec, build_policy
from agents.benchmark.protocol import resolve_tier
from auv_follow_env.layout import OBS_INDEX_V1

__all__ = ["rollout_episode", "replay_traces"]


def rollout_episode(policy: Any, env_id: str, seed: int) -> pd.DataFrame:
    """One episode, per step: time, follower pose, true target and reference, the target the
    follower received (world frame), the policy's own reference (if it has one), forces and
    along-/cross-track error."""
    env = gym.make(env_id)
    spec = env.unwrapped.task_spec
    limits = np.asarray(spec.force_limits)
    obs, info = env.reset(seed=int(seed))
    if hasattr(policy, "reset"):
        policy.reset()
    rows, start = [], True
    i = OBS_INDEX_V1
    while True:
        action, _ = policy.predict(obs, episode_start=np.array([start]), deterministic=True)
        start = False
        obs, _, term, trunc, info = env.step(action)
        x, y, psi = (float(v) for v in info["follower_pose"])
        tx, ty, tpsi = (float(v) for v in info["true_target"][:3])
        rx, ry = (float(v) for v in info["true_reference"][:2])
        c, s = np.cos(psi), np.sin(psi)
        has = obs.shape[-1] <= i["has_packet"] or obs[i["has_packet"]] > 0.5
        dx, dy = float(obs[i["target_dx"]]), float(obs[i["target_dy"]])
        row = {"time": float(info["time"]), "follower_x": x, "follower_y": y, "follower_psi": psi,
               "target_x": tx, "target_y": ty, "target_psi": tpsi, "ref_x": rx, "ref_y": ry,
               "recv_x": x + c * dx - s * dy if has else np.nan, "recv_y": y + s * dx + c * dy if has else np.nan,
               "err": float(info["tracking_error"])}
        if obs.shape[-1] > i["packet_age"]:
            row["packet_age"] = float(obs[i["packet_age"]])
        f = np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[:3], -1, 1) * limits
        row.update({"F_u": f[0], "F_v": f[1], "F_r": f[2]})
        if hasattr(policy, "reference"):
            own = np.asarray(policy.reference(obs)).reshape(-1)[:3]
            ox, oy = x + c * own[0] - s * own[1], y + s * own[0] + c * own[1]
            # estimated target = own reference minus the offset p_d rotated by the estimated heading
            opsi = psi + own[2] - spec.psi_d
            px, py = spec.p_d
            row.update({"own_ref_x": ox, "own_ref_y": oy,
                        "est_x": ox - (np.cos(opsi) * px - np.sin(opsi) * py),
                        "est_y": oy - (np.sin(opsi) * px + np.cos(opsi) * py)})
        ex, ey = rx - x, ry - y
        row["along_track"] = -(ex * np.cos(tpsi) + ey * np.sin(tpsi))  # > 0: follower ahead of the reference
        row["cross_track"] = -(-ex * np.sin(tpsi) + ey * np.cos(tpsi))  # > 0: follower to port of it
        rows.append(row)
        if term or trunc:
            break
    env.close()
    df = pd.DataFrame(rows)
    df.attrs["force_limits"] = tuple(float(v) for v in limits)
    return df


def replay_traces(specs: Sequence[PolicySpec], seed_map: Mapping[str, Sequence[int]], *,
                  progress: bool = False) -> pd.DataFrame:
    """Per-step traces of one episode per (tier, policy): the tier's first seed, the policy's
    first run (what ``auv-follow report`` plots: it never loads a model itself)."""
    frames = []
    for tier, seeds in tqdm(list(seed_map.items()), desc="traces", disable=not progress, leave=False):
        name, env_id = resolve_tier(tier)
        probe = gym.make(env_id)
        task_spec, width = probe.unwrapped.task_spec, int(probe.observation_space.shape[0])
        probe.close()
        for spec in specs:
            if spec.tiers and name not in spec.tiers:
                continue
            try:
                pol = build_policy(spec, spec.runs[0] if spec.runs else None, env_id, task_spec, width)
            except IncompatiblePolicy:
                continue
            try:
                df = rollout_episode(pol, env_id, int(seeds[0]))
            except Exception as exc:  # noqa: BLE001 (a user's controller can raise anything)
                text = " ".join(str(exc).split())[:300]
                raise ValueError(f"policy {spec.label!r} on {name} ({env_id}), seed {int(seeds[0])}: recording its "
                                 f"replay episode (traces.parquet) failed: {type(exc).__name__}"
                                 + (f": {text}" if text else "")) from exc
            df.insert(0, "seed", int(seeds[0]))
            df.insert(0, "policy", spec.label)
            df.insert(0, "tier", name)
            frames.append(df)
    if not frames:
        return pd.DataFrame(columns=["tier", "policy", "seed"])
    out = pd.concat(frames, ignore_index=True)
    floats = [c for c in out.columns if out[c].dtype == np.float64]
    return out.astype({c: np.float32 for c in floats})  # plotted only: half the file size
