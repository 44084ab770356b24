"""Env parameters at the edges: every number and sequence accepted in its natural forms, every
bound enforced with a message naming the argument, and seeds validated before anything changes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from auv_follow_env.params import make_config

# --- item 1: natural forms of numbers and sequences -------------------------------------------

@pytest.mark.parametrize("value", [(-0.65, 0.12), [-0.65, 0.12], np.array([-0.65, 0.12]),
                                   (np.float32(-0.65), np.float64(0.12))])
def test_p_d_accepts_any_real_sequence(value):
    cfg = make_config("S4", p_d=value)
    assert cfg.p_d == pytest.approx((-0.65, 0.12)) and isinstance(cfg.p_d, tuple)


def test_default_tuples_can_be_passed_back():
    base = make_config("S4")
    assert make_config("S4", p_d=base.p_d, force_limits=base.force_limits) == base


@pytest.mark.parametrize("value", ["123", "abc", {"a": 1}, (True, False, True), (1.0, 2.0), {1.0, 2.0, 3.0}])
def test_force_limits_refuses_strings_dicts_bools_and_wrong_lengths(value):
    with pytest.raises(ValueError, match="force_limits"):
        make_config("S4", force_limits=value)


def test_numpy_scalars_are_numbers():
    cfg = make_config("S4", delay_s=np.float32(1.0), physics_substeps=np.int64(3), mismatch=np.float64(0.5))
    assert cfg.delay_s == 1.0 and cfg.physics_substeps == 3 and cfg.mismatch == 0.5
    assert gym.make("AUVFollow-S4-v0", delay_s=np.float32(1.5)).unwrapped.task_spec.delay_steps == 30


@pytest.mark.parametrize("kw,name", [(dict(delay_s="1.0"), "delay_s"), (dict(mismatch=True), "mismatch"),
                                     (dict(physics_substeps=2.0), "physics_substeps"),
                                     (dict(psi_d=[0.1]), "psi_d")])
def test_non_numbers_are_refused_by_name(kw, name):
    with pytest.raises(ValueError, match=name):
        make_config("S4", **kw)


# --- item 6: bounds on resources and physics --------------------------------------------------

@pytest.mark.parametrize("kw,name", [
    (dict(physics_substeps=2**63), "physics_substeps"),
    (dict(physics_substeps=10**9), "physics_substeps"),
    (dict(delay_s=1e9), "delay_s"),
    (dict(dt=1e-12), "dt"),
    (dict(episode_s=1e12), "episode_s"),
    (dict(dt=2.0), "dt"),
    (dict(mismatch=1e300), "mismatch"),
    (dict(mismatch=-0.95), "mismatch"),
    (dict(steady_start_s=60.0), "steady_start_s"),
    (dict(episode_s=5.0), "steady_start_s"),
    (dict(force_limits=(1e9, 1.0, 1.0)), "force_limits"),
    (dict(max_distance_m=float("inf")), "max_distance_m"),
])
def test_out_of_range_values_name_the_argument_and_range(kw, name):
    with pytest.raises(ValueError, match=name) as exc:
        make_config("S4", **kw)
    assert "must be" in str(exc.value)


def test_rk4_stability_bound_names_the_substeps():
    # dt = 0.2 s with 1 substep and 10x damping: h * N_r (1 + m) / I_z = 0.2 * 3 * 11 / 2 = 3.3 > 1
    with pytest.raises(ValueError, match="physics_substeps"):
        make_config("S4", dt=0.2, physics_substeps=1, mismatch=10.0)
    make_config("S4", dt=0.2, physics_substeps=4, mismatch=10.0)  # h = 0.05: 0.83 <= 1, accepted


# --- item 7: seeds and options -----------------------------------------------------------------

def _generators(venv):
    return [None if r is None else r.bit_generator.state["state"]["state"] for r in venv.unwrapped._rngs]


def test_a_bad_seed_list_changes_no_generator():
    venv = gym.make_vec("AUVFollow-S4-v0", num_envs=4)
    venv.reset(seed=100)
    before = _generators(venv)
    with pytest.raises(ValueError, match=r"seed\[2\]=-3"):
        venv.reset(seed=[1, 2, -3, 4])
    assert _generators(venv) == before


@pytest.mark.parametrize("seed", [True, {1, 2, 3, 4}, "1234", 1.5, [1, 2, 3]])
def test_bad_seeds_are_refused(seed):
    venv = gym.make_vec("AUVFollow-S4-v0", num_envs=4)
    with pytest.raises(ValueError, match="seed"):
        venv.reset(seed=seed)


def test_ndarray_and_numpy_seeds_are_accepted_like_lists():
    a = gym.make_vec("AUVFollow-S4-v0", num_envs=3)
    b = gym.make_vec("AUVFollow-S4-v0", num_envs=3)
    oa, _ = a.reset(seed=np.array([5, 6, 7]))
    ob, _ = b.reset(seed=[5, 6, 7])
    np.testing.assert_array_equal(oa, ob)
    oc, _ = b.reset(seed=np.int64(5))
    np.testing.assert_array_equal(oa, oc)


def test_single_env_seed_and_options_checked():
    env = gym.make("AUVFollow-S4-v0")
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=True)
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=-1)
    with pytest.raises(ValueError, match="options"):
        env.reset(seed=0, options=[1])
    o1, _ = env.reset(seed=np.int64(3))
    o2, _ = env.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    venv = gym.make_vec("AUVFollow-S4-v0", num_envs=2)
    with pytest.raises(ValueError, match="options"):
        venv.reset(seed=0, options="reset_mask")
