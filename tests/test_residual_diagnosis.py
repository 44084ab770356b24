"""experiments/residual_diagnosis.py's scripted oracle residual (section 5): its two ends are
known without it. At authority 0 it is the base controller, step for step; at an authority
no difference can exceed (2: actions live in [-1, 1]) it is the same law on the perfect link,
which agents/benchmark/floors.perfect_link_episodes computes by its own loop. Within 1e-5
relative, not exactly: the oracle residual tells each law's disturbance observer the force of
the float64 action it sends, a law alone its own float64 force before the action is rounded
to float32 (differences of 1e-8 to 5e-7 here).
"""

from __future__ import annotations

import numpy as np
import pytest

from agents.benchmark import floors
from experiments import residual_diagnosis as rd

SEEDS = (100, 101)
TIER = "Leader-Hard"


def test_zero_authority_is_the_base():
    base, base_lost = rd.oracle_residual(TIER, SEEDS, None)
    zero, zero_lost = rd.oracle_residual(TIER, SEEDS, 0.0)
    np.testing.assert_allclose(zero, base, rtol=1e-5)
    np.testing.assert_array_equal(zero_lost, base_lost)


def test_full_authority_is_the_law_on_the_perfect_link():
    full, lost = rd.oracle_residual(TIER, SEEDS, 2.0)
    ref = floors.perfect_link_episodes(TIER, list(SEEDS), [rd.BASE]).sort_values("seed")
    np.testing.assert_allclose(full, ref["true_steady_mean"].to_numpy(), rtol=1e-5)
    assert not lost.any() and not ref["terminated"].any()
    # and the information is worth something: the perfect link is far better than the base
    base, _ = rd.oracle_residual(TIER, SEEDS, None)
    assert (full < 0.5 * base).all()


def test_the_imm_fit_scores_with_the_learned_estimators_loss():
    """experiments/imm_same_data.py: its loss of the committed IMM setting on the learned
    estimator's recorded episodes is that recording's own IMM error (the data record the
    committed IMM's error, true minus estimated reference point, as float32)."""
    import gymnasium as gym

    from agents.training.learned_estimator import record_episodes
    from controllers import LEADER_IMM
    from controllers.estimator import EstimatorConfig
    from experiments import imm_same_data as isd
    from experiments.leader_estimators import imm_config

    env_id = "AUVFollow-Leader-Hard-v1"
    data = record_episodes(env_id, isd.TRAIN_FIRST, 8)
    spec = gym.make(env_id).unwrapped.task_spec
    committed = imm_config(EstimatorConfig.for_spec(spec), *(LEADER_IMM["Leader-Hard"][k] for k in isd.KEYS))
    own = float(np.hypot(data["Y"][..., 0], data["Y"][..., 1])[data["M"]].mean())
    assert isd.loss(committed, data, spec) == pytest.approx(own, rel=1e-5)
    # another setting scores differently on the same data (the loss sees the setting)
    other = imm_config(EstimatorConfig.for_spec(spec), 1e-4, 1e-5, 1e-6, 1.0)
    assert abs(isd.loss(other, data, spec) - own) > 1e-3
