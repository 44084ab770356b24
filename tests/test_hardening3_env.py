"""Hardening of the env's keywords: None on a tier, numbers that overflow a float, bools where
numbers are meant, the ranges of make_config, num_envs of the vector env."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from auv_follow_env.params import (
    OVERRIDES,
    OVERRIDES_V1,
    DisturbanceLevel,
    TargetParams,
    VehicleParams,
    make_config,
)
from auv_follow_env.tiers import TIERS, make_tier_config
from auv_follow_env.vector_env import MAX_NUM_ENVS, AUVFollowVectorEnv

HARD = "AUVFollow-Hard-v1"
NUMERIC_V0 = [k for k in OVERRIDES]
NUMERIC_V1 = [k for k in OVERRIDES_V1 if k != "latency_model"]


def test_none_on_a_tier_keeps_the_tiers_range():
    """Reproducer env_none_override.py: ``loss_prob=None`` on Hard-v1 drew loss_prob = 0 at every
    reset (the field's default replaced the tier's range [0.10, 0.25]). None is no override: the
    20 resets draw the same values as the plain tier, all inside its range."""
    env = gym.make(HARD, loss_prob=None)
    ref = gym.make(HARD)
    got = [env.reset(seed=s)[1]["condition"]["loss_prob"] for s in range(20)]
    want = [ref.reset(seed=s)[1]["condition"]["loss_prob"] for s in range(20)]
    assert got == want
    assert all(0.10 <= v <= 0.25 for v in got) and len(set(got)) == 20


@pytest.mark.parametrize("tier", list(TIERS))
def test_none_is_no_override_for_every_keyword_on_every_tier(tier):
    """Every override set to None (the fixed fields such as latency_model='gauss_markov' and
    warmup_s=9 s on Hard, the ranged ones, and those the tier leaves at their defaults) gives
    the tier's own configuration."""
    ref = make_tier_config(tier)
    for key in OVERRIDES + OVERRIDES_V1:
        assert make_tier_config(tier, **{key: None}) == ref, key
    cfg = make_tier_config("Hard", latency_model=None, warmup_s=None, mismatch=None)
    assert cfg.condition.latency_model == "gauss_markov" and cfg.condition.warmup_s == 9.0
    assert cfg.ranges["mismatch"] == (0.60, 1.50)


def test_none_is_no_override_on_v0_and_v1():
    for key in OVERRIDES:
        assert make_config("S2", **{key: None}) == make_config("S2"), key
    for key in OVERRIDES + OVERRIDES_V1:
        assert make_config("S3", version="v1", **{key: None}) == make_config("S3", version="v1"), key


@pytest.mark.parametrize("big", [10**400, -10**400], ids=["10**400", "-10**400"])
def test_a_huge_int_names_the_field(big):
    """Reproducer env_bigint.py: ``loss_prob=10**400`` raised OverflowError('int too large to
    convert to float'). Every numeric keyword of every id family now refuses it with a
    ValueError naming the field, in a message of reasonable length (the number is cut)."""
    with pytest.raises(ValueError, match="loss_prob") as exc:
        gym.make(HARD, loss_prob=big)
    assert len(str(exc.value)) < 400
    cases = [(lambda **kw: make_config("S4", **kw), NUMERIC_V0),
             (lambda **kw: make_config("S4", version="v1", **kw), OVERRIDES + tuple(NUMERIC_V1)),
             (lambda **kw: make_tier_config("Hard", **kw), OVERRIDES + tuple(NUMERIC_V1))]
    for make, keys in cases:
        for key in keys:
            for value in (big, (0.0, big), (big, big), (0.1, 0.1, big)):
                with pytest.raises(ValueError, match=key) as exc:
                    make(**{key: value})
                assert len(str(exc.value)) < 800, key


def test_bools_are_not_numbers_and_numpy_scalars_are():
    for key in NUMERIC_V0:
        with pytest.raises(ValueError, match=key):
            make_config("S4", **{key: True})
    for key in NUMERIC_V1:
        with pytest.raises(ValueError, match=key):
            make_tier_config("Hard", **{key: np.bool_(False)})
    assert make_config("S4", delay_s=np.int64(1), physics_substeps=np.uint8(4)) == \
        make_config("S4", delay_s=1.0, physics_substeps=4)
    assert make_tier_config("Hard", loss_prob=np.float32(0.25)).condition.loss_prob == float(np.float32(0.25))


def test_the_parameter_dataclasses_refuse_huge_ints_and_bools():
    with pytest.raises(ValueError, match="m="):
        VehicleParams(m=10**400)
    with pytest.raises(ValueError, match="surge_amp"):
        TargetParams(speed=0.5, surge_amp=False, surge_period=10.0, yaw_rate_amp=0.0, yaw_period=10.0)
    with pytest.raises(ValueError, match="current_x"):
        DisturbanceLevel(name="x", current_x=(0, 10**400), current_y=(0.0, 0.0), peaks=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="current_y"):
        DisturbanceLevel(name="x", current_x=(0.0, 0.0), current_y=0.1, peaks=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="peaks"):
        DisturbanceLevel(name="x", current_x=(0.0, 0.0), current_y=(0.0, 0.0), peaks=(True, 0.0, 0.0))


def test_ranges_of_make_config_are_checked():
    """``ranges`` (a tier's per-reset ranges) is checked like an override: a pair of finite
    numbers with min <= max of a field that can be drawn, and only on v1."""
    for bad, named in (({"loss_prob": None}, "loss_prob"), ({"loss_prob": (0.3, 0.1)}, "loss_prob"),
                       ({"loss_prob": (0.0, 10**400)}, "loss_prob"), ({"warmup_s": (1.0, 2.0)}, "warmup_s"),
                       ({"loss_prob": "0.1"}, "loss_prob"), ([("loss_prob", (0.0, 0.1))], "ranges")):
        with pytest.raises(ValueError, match=named):
            make_config("S4", version="v1", ranges=bad)
    with pytest.raises(ValueError, match="only on v1"):
        make_config("S4", ranges={"loss_prob": (0.0, 0.1)})
    cfg = make_config("S4", version="v1", ranges={"loss_prob": [0, 0.1]})
    assert cfg.ranges["loss_prob"] == (0.0, 0.1)


def test_num_envs_is_bounded():
    for bad in (10**400, MAX_NUM_ENVS + 1, np.bool_(True), 2.0):
        with pytest.raises(ValueError, match="num_envs"):
            AUVFollowVectorEnv(num_envs=bad)
    with pytest.raises(ValueError, match="num_envs") as exc:
        gym.make_vec("AUVFollow-S4-v0", num_envs=10**400)
    assert len(str(exc.value)) < 400


def test_non_finite_and_wrong_types_stay_value_errors():
    for value in (math.nan, math.inf, "0.1", [0.1], {}, 1j):
        with pytest.raises(ValueError, match="loss_prob") as exc:
            make_tier_config("Hard", loss_prob=value)
        assert not isinstance(exc.value, TypeError)
