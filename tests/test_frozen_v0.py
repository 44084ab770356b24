"""The paper's ids are frozen: v0 trajectories must equal, bit for bit, those recorded from
``main`` at d793f33 (before the v1 link model entered the kernel).

For S1-S4 (``AUVFollow-S{n}-v0``) and seeds 0-4, two policies are run for a full episode:
PROPOSED and uniform random actions (numpy ``default_rng(1000 + seed)``). Every
observation, reward and info array of every step is hashed (SHA-256 of the raw bytes); the
hashes are in ``tests/data/frozen_v0.json``. Regenerate them only for a deliberate,
announced change of v0 (which should instead be a new version):
``python -m tests.test_frozen_v0 --write``.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from controllers import make_controller

DATA = Path(__file__).with_name("data") / "frozen_v0.json"
SCENARIOS = ("S1", "S2", "S3", "S4")
SEEDS = range(5)
POLICIES = ("PROPOSED", "random")


def trajectory_hash(scenario: str, policy: str, seed: int) -> str:
    env = gym.make(f"AUVFollow-{scenario}-v0")
    h = hashlib.sha256()
    obs, info = env.reset(seed=seed)
    ctrl = make_controller("PROPOSED", env.unwrapped.task_spec) if policy == "PROPOSED" else None
    rng = np.random.default_rng(1000 + seed)
    done = False
    while True:
        h.update(np.ascontiguousarray(obs, dtype=np.float32).tobytes())
        for key in ("true_target", "true_reference", "follower_pose"):
            h.update(np.ascontiguousarray(info[key], dtype=np.float64).tobytes())
        h.update(np.float64(info["tracking_error"]).tobytes())
        if done:
            break
        if ctrl is None:
            action = rng.uniform(-1.0, 1.0, 3).astype(np.float32)
        else:
            action, _ = ctrl.predict(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        h.update(np.float64(reward).tobytes())
        done = terminated or truncated
    env.close()
    return h.hexdigest()


def _all_hashes() -> dict[str, str]:
    return {f"{sc}/{pol}/{s}": trajectory_hash(sc, pol, s) for sc in SCENARIOS for pol in POLICIES
            for s in SEEDS}


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("policy", POLICIES)
def test_v0_trajectories_are_frozen(scenario: str, policy: str) -> None:
    expected = json.loads(DATA.read_text())
    for s in SEEDS:
        key = f"{scenario}/{policy}/{s}"
        assert trajectory_hash(scenario, policy, s) == expected[key], f"v0 trajectory {key} changed"


if __name__ == "__main__":
    if "--write" in sys.argv:
        DATA.write_text(json.dumps(_all_hashes(), indent=1, sort_keys=True) + "\n")
        print(f"wrote {DATA}")
