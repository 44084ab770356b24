"""The paper's four controllers on v1 observations (20 fields): the predictor extrapolates over
the observed ``packet_age``, the law holds position before the first packet, and a v1
observation that says "every step a new packet, tau old" gives exactly the v0 forces.

Observations are synthetic (built by field name); expectations are worked out by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from auv_follow_env.layout import OBS_DIM, OBS_DIM_V1, OBS_INDEX_V1
from auv_follow_env.params import make_task_spec
from controllers import ALL_CONTROLLERS, CONTROLLERS, make_controller

S4 = make_task_spec("S4")  # tau = 2 s


def v1_obs(packet_age: float, has_packet: float = 1.0, new_packet: float = 1.0, since_arrival: float = 0.0,
           **fields: float) -> np.ndarray:
    o = np.zeros(OBS_DIM_V1)
    o[OBS_INDEX_V1["cos_psi"]] = 1.0
    if has_packet:
        dpsi = fields.pop("target_dpsi", 0.0)
        o[OBS_INDEX_V1["target_cos_dpsi"]] = math.cos(dpsi)
        o[OBS_INDEX_V1["target_sin_dpsi"]] = math.sin(dpsi)
    for k, v in fields.items():
        o[OBS_INDEX_V1[k]] = v
    o[OBS_INDEX_V1["packet_age"]] = packet_age
    o[OBS_INDEX_V1["since_arrival"]] = since_arrival
    o[OBS_INDEX_V1["new_packet"]] = new_packet
    o[OBS_INDEX_V1["has_packet"]] = has_packet
    return o


@pytest.mark.parametrize("age", [0.3, 1.7, 3.25])
def test_predictor_extrapolates_over_the_packet_age(age):
    """Straight target 2 m ahead heading +x at 0.5 m/s: x_hat = 2 + 0.5 age; the reference is
    p_d behind it: (2 + 0.5 age - 0.65, 0.12)."""
    obs = v1_obs(age, target_dx=2.0, target_u=0.5)
    ref = make_controller("PROPOSED", S4).reference(obs)[0]
    np.testing.assert_allclose(ref, [2.0 + 0.5 * age - 0.65, 0.12, 0.0], atol=1e-12)
    ref_ro = make_controller("ROBUST_ONLY", S4).reference(obs)[0]  # no prediction: the packet's pose
    np.testing.assert_allclose(ref_ro, [2.0 - 0.65, 0.12, 0.0], atol=1e-12)


def test_packet_age_is_per_env_in_a_batch():
    obs = np.stack([v1_obs(a, target_dx=1.0, target_u=0.4) for a in (0.5, 2.5)])
    ref = make_controller("PRED_ONLY", S4).reference(obs)
    np.testing.assert_allclose(ref[:, 0], [1.0 + 0.2 - 0.65, 1.0 + 1.0 - 0.65], atol=1e-12)


@pytest.mark.parametrize("name", CONTROLLERS)
def test_without_a_packet_the_paper_controllers_hold_position(name):
    """has_packet = 0 (target fields all 0): reference = the follower itself, and at rest with
    no current the force is exactly 0 (zero desired velocity, nothing to compensate)."""
    c = make_controller(name, S4)
    obs = v1_obs(0.0, has_packet=0.0, new_packet=0.0)
    for _ in range(3):
        a, _ = c.predict(obs)
        np.testing.assert_array_equal(a, np.zeros(3, dtype=np.float32))
    np.testing.assert_array_equal(c.reference(obs)[0], np.zeros(3))


@pytest.mark.parametrize("name", CONTROLLERS)
def test_a_v0_like_v1_observation_gives_the_v0_forces_exactly(name):
    """v0 is v1 with packet_age = tau, since_arrival = 0, new_packet = has_packet = 1."""
    rng = np.random.default_rng(3)
    c0, c1 = make_controller(name, S4), make_controller(name, S4)
    for _ in range(20):
        o0 = rng.normal(scale=0.5, size=(4, OBS_DIM))
        o1 = np.concatenate([o0, np.tile([S4.delay_s, 0.0, 1.0, 1.0], (4, 1))], axis=1)
        a0, _ = c0.predict(o0)
        a1, _ = c1.predict(o1)
        np.testing.assert_array_equal(a0, a1)
        np.testing.assert_array_equal(c0.reference(o0), c1.reference(o1))


@pytest.mark.parametrize("name", [n for n in ALL_CONTROLLERS if n != "MPC"] + ["MPC"])
def test_every_controller_accepts_both_widths_and_rejects_others(name):
    c = make_controller(name, S4)
    assert c.predict(np.zeros(OBS_DIM))[0].shape == (3,)
    c.reset()
    assert c.predict(np.zeros((2, OBS_DIM_V1)))[0].shape == (2, 3)
    with pytest.raises(ValueError, match="20"):
        c.predict(np.zeros(OBS_DIM + 1))


@pytest.mark.parametrize("name", ["PROPOSED_KF", "PROPOSED_KF_DOB", "MPC"])
def test_our_controllers_hold_position_without_a_packet(name):
    c = make_controller(name, S4)
    obs = v1_obs(0.0, has_packet=0.0, new_packet=0.0)
    for _ in range(3):
        a, _ = c.predict(obs)
        np.testing.assert_allclose(a, 0.0, atol=1e-6)
    np.testing.assert_array_equal(c.reference(obs)[0], np.zeros(3))
