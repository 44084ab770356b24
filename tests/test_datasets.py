"""``auv-follow dataset``: Minari datasets of a policy's episodes (docs/data.md).

The expected values come from re-running the episodes with gym.make and the controller in this
file (and Minari's own reader), not from the writer."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

minari = pytest.importorskip("minari", reason="Minari is not installed (pip install -e '.[data]')")

import auv_follow_env  # noqa: E402,F401
from agents.cli import main  # noqa: E402
from auv_follow_env.layout import OBS_INDEX_V1 as IX  # noqa: E402
from controllers import make_controller  # noqa: E402


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return tmp_path / "minari"


def _rerun(env_id, controller, seed):
    env = gym.make(env_id)
    pol = make_controller(controller, env.unwrapped.task_spec)
    obs, info = env.reset(seed=seed)
    pol.reset()
    observations, actions, rewards, errors, cond = [obs], [], [], [info["tracking_error"]], info.get("condition")
    done = False
    while not done:
        a = pol.predict(obs)[0]
        obs, r, term, trunc, info = env.step(a)
        observations.append(obs)
        actions.append(a)
        rewards.append(r)
        errors.append(info["tracking_error"])
        done = term or trunc
    return np.array(observations), np.array(actions), np.array(rewards), np.array(errors), cond, term


def test_dataset_holds_the_episodes_and_their_facts(store, capsys):
    assert main(["dataset", "--tier", "Leader-Easy", "--policy", "PROPOSED_KF_DOB", "--seeds", "4,9",
                 "--id", "test/leader-easy-kf-v0", "--ref-episodes", "2", "--ref-max", "PROPOSED_KF_DOB",
                 "--no-progress"]) == 0
    assert "test/leader-easy-kf-v0" in capsys.readouterr().out
    ds = minari.load_dataset("test/leader-easy-kf-v0")
    assert ds.total_episodes == 2 and ds.total_steps == 2 * 1200
    meta = list(ds.storage.get_episode_metadata([0, 1]))
    for ep, m, seed in zip(ds.iterate_episodes(), meta, (4, 9), strict=True):
        obs, act, rew, err, cond, term = _rerun("AUVFollow-Leader-Easy-v1", "PROPOSED_KF_DOB", seed)
        assert m["seed"] == seed and m["env_id"] == "AUVFollow-Leader-Easy-v1"
        assert m["condition"]["latency_s"] == pytest.approx(cond["latency_s"])
        assert m["condition"]["leader_modes"] == cond["leader_modes"] and m["condition"]["latency_model"] == \
            cond["latency_model"]
        np.testing.assert_array_equal(ep.observations, obs)
        np.testing.assert_allclose(ep.actions, act, rtol=0, atol=1e-6)  # (stored as float32)
        np.testing.assert_allclose(ep.rewards, rew, rtol=1e-12)
        assert not ep.terminations.any() and ep.truncations[-1] and not term
        np.testing.assert_allclose(ep.infos["tracking_error"], err, rtol=1e-12)
        np.testing.assert_array_equal(ep.infos["new_packet"], obs[:, IX["new_packet"]])
        np.testing.assert_array_equal(ep.infos["packet_age"], obs[:, IX["packet_age"]].astype(np.float64))
    # the reference scores: mean returns on the tier's first two published test seeds
    from auv_follow_env import ALL_TIERS

    test_seeds = ALL_TIERS["Leader-Easy"].test_seeds[:2]
    pid = np.mean([_rerun("AUVFollow-Leader-Easy-v1", "PID", s)[2].sum() for s in test_seeds])
    kf = np.mean([_rerun("AUVFollow-Leader-Easy-v1", "PROPOSED_KF_DOB", s)[2].sum() for s in test_seeds])
    assert ds.storage.metadata["ref_min_score"] == pytest.approx(pid, rel=1e-9)
    assert ds.storage.metadata["ref_max_score"] == pytest.approx(kf, rel=1e-9)
    assert minari.get_normalized_score(ds, np.array([pid, kf])) == pytest.approx([0.0, 1.0])
    env = ds.recover_environment()
    assert env.spec.id == "AUVFollow-Leader-Easy-v1"
    np.testing.assert_array_equal(env.reset(seed=4)[0], next(ds.iterate_episodes()).observations[0])


def test_dataset_refusals_come_before_any_work(store, capsys):
    def refused(*args):
        with pytest.raises(SystemExit) as e:
            main(["dataset", "--tier", "Hard", "--policy", "PID", "--ref-episodes", "1", "--no-progress", *args])
        return e.value.code, capsys.readouterr().err

    for bad in ("hard-pid", "hard-pid-v0", "t/hard-pid-v0", "tests/hard pid-v0", "tests/hard-pid"):
        code, err = refused("--id", bad, "--seeds", "0")
        assert code == 2 and "argument --id" in err and "NAMESPACE/NAME-vN" in err, bad
    code, err = refused("--id", "tests/hard-pid-v0", "--seeds", "3000000-3000001")
    assert code == 2 and "2 of the seeds are test seeds of Hard" in err and "leaks" in err
    code, err = refused("--id", "tests/hard-pid-v0", "--seeds", "0", "--ref-max", "NOPE")
    assert code == 2 and "argument --ref-max" in err
    assert not store.exists() or not any(store.rglob("*.json"))
    # a test seed with the flag is recorded; the same id again is refused
    assert main(["dataset", "--tier", "Hard", "--policy", "PID", "--seeds", "3000000", "--allow-test-seeds",
                 "--id", "tests/hard-pid-v0", "--ref-episodes", "1", "--ref-max", "PID", "--no-progress"]) == 0
    code, err = refused("--id", "tests/hard-pid-v0", "--seeds", "0")
    assert code == 2 and "exists in" in err
