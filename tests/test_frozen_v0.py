"""The paper's ids are frozen *in behaviour*: v0 trajectories must stay within a tolerance of the
golden arrays recorded before 0.2.0 (glibc libm sin/cos, before the SIMD sin/cos became the
default).

For S1-S4 (``AUVFollow-S{n}-v0``) and seeds 0-2, two policies are run for a full episode:
PROPOSED and uniform random actions (numpy ``default_rng(1000 + seed)``). Every step's
observation, reward, ``true_target``, ``true_reference``, ``follower_pose`` and
``tracking_error`` (the reset's included, with reward 0) are recorded in
``tests/data/frozen_v0.npz``. The contract:

* float64 arrays (reward and the info arrays) within 1e-9 relative, or 1e-12 absolute where the
  value is near zero (``|got - golden| <= 1e-12 + 1e-9 |golden|``);
* observations are float32: rounding a float64 value that moved by 1e-15 to float32 can land on
  the neighbouring float32, one float32 ULP (2^-23 relative) away, so they are compared within
  that, ``|got - golden| <= 1e-12 + 2^-23 |golden|`` (their own precision, not 1e-9);
* the episode ends at the same step.

Bit identity is not the contract: it never held across hosts (glibc versions and CPU features
change last bits). Determinism within one host is exact, and tested below and in
tests/test_env.py. Regenerate the golden file only for a deliberate, announced change of v0
(which should instead be a new version): ``python -m tests.test_frozen_v0 --write``
(records with ``sincos="libm"``, the path the file was first recorded with).
"""

from __future__ import annotations

import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from auv_follow_env.vector_env import AUVFollowVectorEnv
from controllers import make_controller

DATA = Path(__file__).with_name("data") / "frozen_v0.npz"
SCENARIOS = ("S1", "S2", "S3", "S4")
SEEDS = range(3)
POLICIES = ("PROPOSED", "random")
FIELDS = ("obs", "reward", "true_target", "true_reference", "follower_pose", "tracking_error")
RTOL64, ATOL = 1e-9, 1e-12
RTOL32 = 2.0**-23  # one float32 ULP, relative


def trajectory(scenario: str, policy: str, seed: int, **env_kwargs) -> dict[str, np.ndarray]:
    """Every step's arrays of one full episode (row 0: the reset, reward 0)."""
    env = gym.make(f"AUVFollow-{scenario}-v0", **env_kwargs)
    obs, info = env.reset(seed=seed)
    ctrl = make_controller("PROPOSED", env.unwrapped.task_spec) if policy == "PROPOSED" else None
    rng = np.random.default_rng(1000 + seed)
    rows: dict[str, list] = {f: [] for f in FIELDS}
    reward, done = 0.0, False
    while True:
        rows["obs"].append(np.array(obs, dtype=np.float32))
        rows["reward"].append(reward)
        for key in ("true_target", "true_reference", "follower_pose"):
            rows[key].append(np.array(info[key], dtype=np.float64))
        rows["tracking_error"].append(float(info["tracking_error"]))
        if done:
            break
        if ctrl is None:
            action = rng.uniform(-1.0, 1.0, 3).astype(np.float32)
        else:
            action, _ = ctrl.predict(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    env.close()
    return {f: np.array(v, dtype=np.float32 if f == "obs" else np.float64) for f, v in rows.items()}


def _key(scenario: str, policy: str, seed: int, field: str) -> str:
    return f"{scenario}/{policy}/{seed}/{field}"


def deviation(got: dict[str, np.ndarray], golden: dict[str, np.ndarray]) -> dict[str, float]:
    """Per field: the largest |got - golden| in units of the contract's tolerance (<= 1 passes),
    and the largest absolute and relative differences (``abs_*``, ``rel_*``)."""
    out = {}
    for f in FIELDS:
        g, e = got[f].astype(np.float64), golden[f].astype(np.float64)
        d = np.abs(g - e)
        rtol = RTOL32 if f == "obs" else RTOL64
        out[f] = float((d / (ATOL + rtol * np.abs(e))).max())
        out["abs_" + f] = float(d.max())
        big = np.abs(e) > 1e-3
        out["rel_" + f] = float((d[big] / np.abs(e[big])).max()) if big.any() else 0.0
    return out


@pytest.fixture(scope="module")
def golden() -> dict[str, np.ndarray]:
    with np.load(DATA) as z:
        return {k: z[k] for k in z.files}


def _check(got: dict[str, np.ndarray], golden: dict[str, np.ndarray], scenario: str, policy: str, seed: int):
    exp = {f: golden[_key(scenario, policy, seed, f)] for f in FIELDS}
    assert got["reward"].shape == exp["reward"].shape, f"{scenario}/{policy}/{seed}: the episode ends elsewhere"
    for f in FIELDS:
        rtol = RTOL32 if f == "obs" else RTOL64
        np.testing.assert_allclose(got[f], exp[f], rtol=rtol, atol=ATOL,
                                   err_msg=f"v0 trajectory {scenario}/{policy}/{seed}: {f} changed")


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("policy", POLICIES)
def test_v0_trajectories_are_frozen(scenario: str, policy: str, golden) -> None:
    for s in SEEDS:
        _check(trajectory(scenario, policy, s), golden, scenario, policy, s)


def test_golden_file_is_complete_and_small(golden) -> None:
    assert DATA.stat().st_size < 5e6
    for sc in SCENARIOS:
        for pol in POLICIES:
            for s in SEEDS:
                n = golden[_key(sc, pol, s, "reward")].shape[0]
                if pol == "PROPOSED":  # 60 s of 0.05 s steps and the reset: PROPOSED never terminates
                    assert n == 1201, (sc, pol, s)
                assert all(golden[_key(sc, pol, s, f)].shape[0] == n for f in FIELDS)
                assert golden[_key(sc, pol, s, "obs")].shape == (n, 16)
                assert golden[_key(sc, pol, s, "obs")].dtype == np.float32


def test_the_contract_rejects_a_change_of_one_part_in_1e8(golden) -> None:
    """The comparison is not vacuous: a relative change of 1e-8 in one value of one array fails."""
    exp = {f: golden[_key("S4", "PROPOSED", 0, f)] for f in FIELDS}
    for f in ("reward", "follower_pose", "obs"):
        got = {k: v.copy() for k, v in exp.items()}
        flat = got[f].reshape(-1)
        j = int(np.argmax(np.abs(flat)))
        flat[j] = flat[j] * (1.0 + (1e-6 if f == "obs" else 1e-8))
        with pytest.raises(AssertionError, match=f"{f} changed"):
            _check(got, golden, "S4", "PROPOSED", 0)


@pytest.mark.parametrize("scenario", ["S2", "S4"])
def test_same_seed_same_bits_single_env(scenario: str) -> None:
    """Determinism within one host and build is exact: two runs of a seed give the same bits."""
    a = trajectory(scenario, "random", 7)
    b = trajectory(scenario, "random", 7)
    for f in FIELDS:
        assert np.array_equal(a[f].view(np.uint8), b[f].view(np.uint8)), f


@pytest.mark.parametrize("env_id", ["AUVFollow-S4-v0", "AUVFollow-Hard-v1"])
def test_same_seed_same_bits_vector_env(env_id: str) -> None:
    acts = np.random.default_rng(5).uniform(-1, 1, (300, 64, 3)).astype(np.float32)

    def run() -> list[np.ndarray]:
        venv = gym.make_vec(env_id, num_envs=64, vectorization_mode="vector_entry_point", episode_s=5.0,
                            steady_start_s=1.0, max_episode_steps=100)
        obs, info = venv.reset(seed=123)
        out = [obs, info["true_target"]]
        for a in acts:  # three episodes with autoresets
            obs, rew, term, trunc, info = venv.step(a)
            out += [obs, rew, term, trunc, info["true_target"], info["follower_pose"]]
        out.append(venv.unwrapped._sim.state.copy())
        venv.close()
        return out

    for x, y in zip(run(), run(), strict=True):
        assert np.array_equal(x.view(np.uint8), y.view(np.uint8))


def test_vector_env_matches_the_golden_arrays(golden) -> None:
    """The vector env, env by env, under the same contract (PROPOSED, batched, seeds 0-2)."""
    for scenario in SCENARIOS:
        venv = AUVFollowVectorEnv(num_envs=len(SEEDS), scenario=scenario, parallel=False)
        spec = venv.task_spec
        ctrl = make_controller("PROPOSED", spec)
        obs, info = venv.reset(seed=list(SEEDS))
        rows: dict[str, list] = {f: [] for f in FIELDS}
        reward = np.zeros(len(SEEDS))
        first = np.ones(len(SEEDS), dtype=bool)
        for step in range(spec.n_steps + 1):
            rows["obs"].append(obs.copy())
            rows["reward"].append(reward.copy())
            for key in ("true_target", "true_reference", "follower_pose", "tracking_error"):
                rows[key].append(np.array(info[key], dtype=np.float64))
            if step == spec.n_steps:
                break
            action, _ = ctrl.predict(obs, episode_start=first)
            first[:] = False
            obs, reward, _term, _trunc, info = venv.step(action)
        venv.close()
        for j, s in enumerate(SEEDS):
            got = {f: np.array([r[j] for r in v]) for f, v in rows.items()}
            got["obs"] = got["obs"].astype(np.float32)
            _check(got, golden, scenario, "PROPOSED", s)


def write() -> None:
    arrays = {}
    for sc in SCENARIOS:
        for pol in POLICIES:
            for s in SEEDS:
                tr = trajectory(sc, pol, s, **_LIBM)
                for f in FIELDS:
                    arrays[_key(sc, pol, s, f)] = tr[f]
    np.savez_compressed(DATA, **arrays)
    print(f"wrote {DATA} ({DATA.stat().st_size / 1e6:.2f} MB)")


_LIBM = {"sincos": "libm"}  # the path the golden arrays were recorded with (the 0.1.0 default)

if __name__ == "__main__":
    if "--write" in sys.argv:
        write()
