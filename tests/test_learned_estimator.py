"""The learned estimator of the Leader tiers (agents/training/learned_estimator.py): with a zero
correction it is PROPOSED_IMM_DOB, a constant correction shifts the estimate by exactly that, a
peek leaves the GRU's state alone, a reset forgets it, and a run directory loads and scores like a
trained agent."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from controllers import make_controller

HARD = "AUVFollow-Leader-Hard-v1"


def _spec():
    env = gym.make(HARD)
    spec = env.unwrapped.task_spec
    env.close()
    return spec


def _weights(seed: int = 0, bias=(0.0, 0.0), zero_head: bool = False) -> dict:
    import torch

    from agents.training.learned_estimator import N_FEATURES, _network

    torch.manual_seed(seed)
    net = _network(8)
    with torch.no_grad():
        if zero_head:
            net.head[2].weight.zero_()
        net.head[2].bias.copy_(torch.tensor(bias))
    return {"hidden": 8, "state_dict": net.state_dict(), "feat_mean": torch.zeros(N_FEATURES),
            "feat_std": torch.ones(N_FEATURES)}


def _episode(n: int = 4, steps: int = 200, seed: int = 300):
    venv = gym.make_vec(HARD, num_envs=n, vectorization_mode="vector_entry_point")
    obs, _ = venv.reset(seed=seed)
    ctrl = make_controller("PROPOSED_IMM_DOB", venv.unwrapped.task_spec)
    out = [obs]
    start = np.ones(n, bool)
    for _ in range(steps):
        a, _ = ctrl.predict(obs, episode_start=start)
        start[:] = False
        obs, *_ = venv.step(a)
        out.append(obs)
    venv.close()
    return np.array(out)


def test_zero_correction_is_the_generic_classical():
    """Head weights and bias zero: the estimate and the actions are PROPOSED_IMM_DOB's, step for step
    (the same IMM on the same observations, plus 0)."""
    from agents.training.learned_estimator import make_controller_from

    spec = _spec()
    O = _episode()
    base = make_controller("PROPOSED_IMM_DOB", spec)
    learned = make_controller_from(spec, _weights(zero_head=True))
    start = np.ones(O.shape[1], bool)
    for k in range(O.shape[0]):
        a0, _ = base.predict(O[k], episode_start=start)
        a1, _ = learned.predict(O[k], episode_start=start)
        np.testing.assert_array_equal(a1, a0)
        start[:] = False


def test_constant_correction_shifts_the_estimate_by_exactly_it():
    """Head weights zero and bias (0.3, -0.2): the estimate's body-frame position is the IMM's plus
    (0.3, -0.2) m wherever the IMM has a fix, and the IMM's (zeros) where it has none."""
    from agents.training.learned_estimator import LearnedEstimator, _imm

    spec = _spec()
    O = _episode(steps=120)
    O[:5, 0, 5:14] = 0.0  # env 0 hears nothing for its first 5 steps (has_packet = 0: the layout's zeros)
    O[:5, 0, 16:20] = 0.0
    imm, learned = _imm(spec), LearnedEstimator(spec, _weights(bias=(0.3, -0.2), zero_head=True))
    start = np.ones(O.shape[1], bool)
    seen_invalid = seen_valid = False
    for k in range(O.shape[0]):
        e0 = imm.step(O[k], start, with_cov=False)
        e1 = learned.step(O[k], start, with_cov=False)
        start[:] = False
        v = e0.valid
        seen_valid |= v.any()
        seen_invalid |= (~v).any()
        np.testing.assert_allclose(e1.rel_x[v], e0.rel_x[v] + 0.3, rtol=0, atol=1e-6)
        np.testing.assert_allclose(e1.rel_y[v], e0.rel_y[v] - 0.2, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(e1.rel_x[~v], e0.rel_x[~v])
        np.testing.assert_array_equal(e1.rel_psi, e0.rel_psi)
    assert seen_valid and seen_invalid


def test_a_peek_leaves_the_state_and_a_reset_forgets_it():
    """reference() before each predict() (as evaluate_batched does) changes no action; an env reset
    mid-run gives the estimate of a fresh estimator on the same observations."""
    from agents.training.learned_estimator import LearnedEstimator, make_controller_from

    spec = _spec()
    O = _episode(steps=150)
    w = _weights(seed=3)
    a, b = make_controller_from(spec, w), make_controller_from(spec, w)
    start = np.ones(O.shape[1], bool)
    for k in range(O.shape[0]):
        b.reference(O[k])
        np.testing.assert_array_equal(b.predict(O[k], episode_start=start)[0], a.predict(O[k], episode_start=start)[0])
        start[:] = False
    long, fresh = LearnedEstimator(spec, w), LearnedEstimator(spec, w)
    n = O.shape[1]
    for k in range(100):
        long.step(O[k], np.full(n, k == 0), with_cov=False)
    for k in range(100, O.shape[0]):
        e_long = long.step(O[k], np.full(n, k == 100), with_cov=False)
        e_fresh = fresh.step(O[k], np.full(n, k == 100), with_cov=False)
        np.testing.assert_array_equal(e_long.rel_x, e_fresh.rel_x)
        np.testing.assert_array_equal(e_long.rel_y, e_fresh.rel_y)


def test_recording_refuses_test_seeds_and_other_tiers():
    from agents.training.learned_estimator import record_episodes

    with pytest.raises(ValueError, match="seed"):
        record_episodes(HARD, 7_000_000, 2)
    with pytest.raises(ValueError, match="Leader"):
        record_episodes("AUVFollow-Hard-v1", 0, 2)


def test_a_trained_run_loads_and_is_scored_with_its_base(tmp_path):
    """A tiny run: its targets are the true minus the IMM's reference point (so a perfect network
    would score 0), it writes model.zip, config.yaml and curve.csv, load_agent gives a policy whose
    actions are in the box, and the benchmark reads PROPOSED_IMM_DOB as its base."""
    from agents.benchmark.policies import parse_policy, residual_bases
    from agents.training.learned_estimator import EstimatorSettings, train_estimator
    from agents.training.loading import load_agent

    run = train_estimator(HARD, tmp_path / "le", seed=1, n_train=4, n_val=2,
                          settings=EstimatorSettings(hidden=8, epochs=1, batch=4, chunk=400), progress=False)
    assert {p.name for p in run.iterdir()} >= {"model.zip", "config.yaml", "curve.csv"}
    agent = load_agent(run)
    O = _episode(n=3, steps=60)
    start = np.ones(3, bool)
    for k in range(O.shape[0]):
        act, _ = agent.predict(O[k], episode_start=start)
        start[:] = False
        assert act.shape == (3, 3) and np.all(np.abs(act) <= 1.0)
    spec = parse_policy(f"LE={run}")
    assert spec.kind == "learned"
    assert residual_bases([spec]) == {"LE": "PROPOSED_IMM_DOB"}


def test_record_targets_are_the_true_minus_the_imm_reference():
    """On the recorded steps, the IMM's reference point (features 20, 21) plus the target equals the
    true reference point in the follower's body frame, worked out here from the env's info."""
    from agents.training.learned_estimator import record_episodes

    data = record_episodes(HARD, 400, 2)
    X, Y, M = data["X"], data["Y"], data["M"]
    assert M.sum() > 1000
    venv = gym.make_vec(HARD, num_envs=2, vectorization_mode="vector_entry_point")
    _, info = venv.reset(seed=400)
    fol, tr = info["follower_pose"], info["true_reference"]
    venv.close()
    c, s = np.cos(fol[:, 2]), np.sin(fol[:, 2])
    dx, dy = tr[:, 0] - fol[:, 0], tr[:, 1] - fol[:, 1]
    np.testing.assert_allclose(X[0, :, 20] + Y[0, :, 0], c * dx + s * dy, atol=1e-5)
    np.testing.assert_allclose(X[0, :, 21] + Y[0, :, 1], -s * dx + c * dy, atol=1e-5)
