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
