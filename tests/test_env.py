"""The Gymnasium envs: API conformance, registration, overrides, determinism, input
validation, episode end, observation content, rendering and vectorisation."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env
from auv_follow_env import dynamics as dyn
from auv_follow_env.env import AUVFollowEnv
from auv_follow_env.layout import OBS_DIM, OBS_FIELDS, OBS_INDEX, decode
from auv_follow_env.metrics import tracking_metrics

S4 = "AUVFollow-S4-v0"
DT = 0.05
N_STEPS = 1200


def _sim_snapshot(env) -> dict[str, np.ndarray]:
    sim = env.unwrapped._sim
    names = ("state", "k", "proc", "queue", "rs", "params", "obs", "truth", "err_hist", "err_stage", "rew", "term")
    snap = {n: getattr(sim, n).copy() for n in names}
    snap["rng"] = env.unwrapped.np_random.bit_generator.state
    return snap


def _assert_same_snapshot(a, b):
    assert a.keys() == b.keys()
    for n in a:
        if n == "rng":
            assert a[n] == b[n]
        else:
            np.testing.assert_array_equal(a[n], b[n], err_msg=n)


# --- API conformance and registration ---------------------------------------------------

@pytest.mark.parametrize("env_id", auv_follow_env.ENV_IDS)
def test_gymnasium_check_env(env_id):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # any checker warning fails the test ...
        # ... except the unbounded observation Box, which is by design (documented in the env)
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is")
        check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("env_id", auv_follow_env.ENV_IDS)
def test_sb3_check_env(env_id):
    from stable_baselines3.common.env_checker import check_env

    env = gym.make(env_id)
    check_env(env.unwrapped, warn=True)
    env.close()


def test_env_ids():
    assert set(auv_follow_env.ENV_IDS) == {"AUVFollow-S1-v0", "AUVFollow-S2-v0", "AUVFollow-S3-v0",
                                           "AUVFollow-S4-v0", "AUVFollow-v0"}
    for env_id in auv_follow_env.ENV_IDS:
        assert gym.spec(env_id).max_episode_steps is None  # the env truncates itself (see __init__)


def test_make_with_module_prefix_in_fresh_process():
    code = ("import sys, gymnasium as gym\n"
            "assert 'auv_follow_env' not in sys.modules\n"
            "env = gym.make('auv_follow_env:AUVFollow-S4-v0')\n"
            "obs, info = env.reset(seed=0)\n"
            "obs, r, term, trunc, info = env.step(env.action_space.sample())\n"
            "print(obs.shape, env.unwrapped.task_spec.scenario, env.spec.max_episode_steps)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "(16,) S4 None"


def test_overrides_through_make():
    env = gym.make(S4, disturbance="L1")
    ts = env.unwrapped.task_spec
    assert (ts.scenario, ts.disturbance, ts.delay_s, ts.delay_steps) == ("S4", "L1", 2.0, 40)
    env.reset(seed=0)
    p = env.unwrapped._sim.params[0]
    # Table 3 L1: current x in [0.01, 0.03] -> mean 0.02, amplitude 0.01; y in [-0.018, 0.002]
    assert p[dyn.P_CX] == pytest.approx(0.02) and p[dyn.P_CX + 1] == pytest.approx(0.01)
    assert p[dyn.P_CY] == pytest.approx(-0.008) and p[dyn.P_CY + 1] == pytest.approx(0.01)
    # peak d_u = 0.02 per unit mass, m = 25 kg, first tone weight 0.6 -> 0.3 N
    assert p[dyn.P_D] == pytest.approx(0.6 * 0.02 * 25.0)
    # damping mismatch of S4: +105 % on X_u = 15 N s/m
    assert p[dyn.P_XU] == pytest.approx(15.0 * 2.05)
    env.close()

    env = gym.make("AUVFollow-v0", scenario="S2", delay_s=1.5)
    ts = env.unwrapped.task_spec
    assert (ts.scenario, ts.disturbance, ts.delay_s, ts.delay_steps) == ("S2", "L1", 1.5, 30)
    assert env.unwrapped.config.mismatch == 0.60
    env.close()

    ts = gym.make("AUVFollow-v0").unwrapped.task_spec  # default scenario
    assert ts.scenario == "S4" and ts.delay_s == 2.0 and ts.disturbance == "L2"


def test_task_spec_is_immutable():
    ts = gym.make(S4).unwrapped.task_spec
    with pytest.raises(AttributeError):
        ts.delay_s = 0.0  # type: ignore[misc]


# --- determinism ------------------------------------------------------------------------

def _rollout(env_id, seed, action_seed, n=N_STEPS, **kw):
    kw.setdefault("max_distance_m", 1e3)  # random actions drift away; keep the whole episode
    env = gym.make(env_id, **kw)
    actions = np.random.default_rng(action_seed).uniform(-1, 1, (n, 3)).astype(np.float32)
    obs, info = env.reset(seed=seed)
    O, R, T = [obs], [], [info["true_target"].copy()]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        O.append(obs)
        R.append(r)
        T.append(info["true_target"].copy())
        if term or trunc:
            break
    params = env.unwrapped._sim.params[0].copy()
    env.close()
    return np.array(O), np.array(R), np.array(T), params, term, trunc


def test_same_seed_bit_identical_full_episode():
    a = _rollout(S4, 123, 7)
    b = _rollout(S4, 123, 7)
    assert len(a[1]) == N_STEPS and a[5] and not a[4]
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])


def test_different_seeds_differ():
    a = _rollout(S4, 1, 7, n=200)
    b = _rollout(S4, 2, 7, n=200)
    assert not np.array_equal(a[3], b[3])  # different phases / current periods
    assert np.abs(a[2][-1, :2] - b[2][-1, :2]).max() > 1e-3  # different target trajectories
    # the fixed parts of the row (plant, target speed, levels) are the same
    fixed = list(range(dyn.P_M, dyn.P_TPU)) + [dyn.P_TAR, dyn.P_TWR, dyn.P_CX, dyn.P_CX + 1, dyn.P_CY]
    np.testing.assert_array_equal(a[3][fixed], b[3][fixed])


def test_reset_reseeds_and_unseeded_reset_continues_the_stream():
    env = gym.make(S4)
    o1, _ = env.reset(seed=5)
    p1 = env.unwrapped._sim.params[0].copy()
    env.reset()
    p2 = env.unwrapped._sim.params[0].copy()
    assert not np.array_equal(p1, p2)
    o3, _ = env.reset(seed=5)
    np.testing.assert_array_equal(o1, o3)
    np.testing.assert_array_equal(p1, env.unwrapped._sim.params[0])


# --- input validation -------------------------------------------------------------------

BAD_ACTIONS = [
    ("nan", np.array([np.nan, 0.0, 0.0], dtype=np.float32), "NaN or inf"),
    ("inf", np.array([0.0, np.inf, 0.0]), "NaN or inf"),
    ("-inf list", [0.0, 0.0, -np.inf], "NaN or inf"),
    ("shape (2,)", np.zeros(2, dtype=np.float32), "shape"),
    ("shape (3,1)", np.zeros((3, 1), dtype=np.float32), "shape"),
    ("shape ()", np.float32(0.0), "shape"),
    ("list of 2", [0.1, 0.2], "shape"),
    ("str dtype", np.array(["a", "b", "c"]), "dtype"),
    ("object dtype", np.array([0.1, None, 0.2], dtype=object), "dtype"),
    ("bool dtype", np.array([True, False, True]), "dtype"),
    ("None", None, "dtype"),
    ("string", "go", "dtype"),
    ("ragged", [[0.1], 0.2, 0.3], "not a numeric array"),
]


@pytest.mark.parametrize("label,action,match", BAD_ACTIONS, ids=[b[0] for b in BAD_ACTIONS])
def test_bad_action_raises_and_changes_nothing(label, action, match):
    rng = np.random.default_rng(0)
    good = rng.uniform(-1, 1, (20, 3)).astype(np.float32)
    env, twin = gym.make(S4), gym.make(S4)
    env.reset(seed=9)
    twin.reset(seed=9)
    for a in good[:5]:
        env.step(a)
        twin.step(a)
    before = _sim_snapshot(env)
    with pytest.raises(ValueError, match=match):
        env.step(action)
    _assert_same_snapshot(before, _sim_snapshot(env))
    for a in good[5:]:
        o1, r1, t1, u1, i1 = env.step(a)
        o2, r2, t2, u2, i2 = twin.step(a)
        np.testing.assert_array_equal(o1, o2)
        assert (r1, t1, u1, i1["time"]) == (r2, t2, u2, i2["time"])
    # the TimeLimit count was not advanced by the failed call
    assert int(env.unwrapped._sim.k[0]) == int(twin.unwrapped._sim.k[0]) == 20


def test_bad_action_partial_nan_in_float64_list():
    env = AUVFollowEnv()
    env.reset(seed=0)
    before = _sim_snapshot(env)
    with pytest.raises(ValueError, match="NaN"):
        env.step([0.5, float("nan"), 0.5])
    _assert_same_snapshot(before, _sim_snapshot(env))


def test_step_before_reset_raises():
    with pytest.raises(RuntimeError, match="reset"):
        AUVFollowEnv().step(np.zeros(3, dtype=np.float32))


@pytest.mark.parametrize("big,clipped", [
    ([5.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
    ([-7.0, 3.0, -2.0], [-1.0, 1.0, -1.0]),
    ([1e30, -0.5, 1.0000001], [1.0, -0.5, 1.0]),
])
def test_out_of_range_actions_are_clipped(big, clipped):
    envs = [gym.make(S4), gym.make(S4)]
    outs = []
    for env, a in zip(envs, (big, clipped), strict=True):
        env.reset(seed=4)
        for _ in range(3):
            res = env.step(np.array(a, dtype=np.float64))
        outs.append((res, env.unwrapped._sim.state.copy()))
    np.testing.assert_array_equal(outs[0][1], outs[1][1])
    np.testing.assert_array_equal(outs[0][0][0], outs[1][0][0])
    assert outs[0][0][1] == outs[1][0][1]


def test_action_types_that_are_accepted():
    # list, float32, float64, int and non-contiguous arrays are the same action
    ref = gym.make(S4)
    ref.reset(seed=2)
    o_ref = ref.step(np.array([1.0, 0.0, -1.0], dtype=np.float32))[0]
    base = np.array([[1.0, 9.0], [0.0, 9.0], [-1.0, 9.0]])
    for a in ([1.0, 0.0, -1.0], (1, 0, -1), np.array([1, 0, -1], dtype=np.int64),
              np.array([1.0, 0.0, -1.0]), base[:, 0]):
        env = gym.make(S4)
        env.reset(seed=2)
        np.testing.assert_array_equal(env.step(a)[0], o_ref)


BAD_KWARGS = [
    (dict(scenario="S9"), "S1.*S4"),
    (dict(scenario=None), "scenario"),
    (dict(disturbance="L7"), "L0.*L2"),
    (dict(delay_s=-0.5), "delay_s"),
    (dict(delay_s=0.33), "delay_s.*multiple"),
    (dict(delay_s=float("nan")), "delay_s"),
    (dict(dt=0.0), "dt"),
    (dict(dt=-0.05), "dt"),
    (dict(dt=float("inf")), "dt"),
    (dict(episode_s=0.0), "episode_s"),
    (dict(episode_s=-60.0), "episode_s"),
    (dict(episode_s=10.01), "episode_s"),
    (dict(physics_substeps=0), "physics_substeps"),
    (dict(physics_substeps=2.5), "physics_substeps"),
    (dict(physics_substeps=True), "physics_substeps"),
    (dict(mismatch=-1.0), "mismatch"),
    (dict(mismatch=-3.0), "mismatch"),
    (dict(mismatch=float("nan")), "mismatch"),
    (dict(max_distance_m=0.0), "max_distance_m"),
    (dict(effort_weight=-1.0), "effort_weight"),
    (dict(force_limits=(150.0, 150.0)), "force_limits"),
    (dict(force_limits=(150.0, 0.0, 30.0)), "force_limits"),
    (dict(p_d=(1.0, float("nan"))), "p_d"),
    (dict(init_offset_m=-1.0), "init_offset_m"),
    (dict(delay="2.0"), "unexpected keyword argument 'delay'"),  # (a TypeError that is also a ValueError)
    (dict(foo=1), "unexpected keyword argument 'foo'"),
    (dict(render_mode="bogus"), "render_mode"),
]


@pytest.mark.parametrize("kw,match", BAD_KWARGS, ids=[str(k) for k, _ in BAD_KWARGS])
def test_bad_config_raises(kw, match):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gym.make warns about the bogus render mode first
        with pytest.raises(ValueError, match=match):
            gym.make("AUVFollow-v0", **kw)
    with pytest.raises(ValueError, match=match):
        AUVFollowEnv(**kw)


@pytest.mark.parametrize("kw,steps", [(dict(episode_s=120.0), 2400), (dict(dt=0.1), 600)])
def test_overridden_episode_length_runs_to_its_end_with_metrics(kw, steps):
    """episode_s / dt through gym.make: the env truncates itself at episode_s / dt steps
    (no registered TimeLimit can cut it short) and the last step carries the metrics."""
    env = gym.make(S4, max_distance_m=1e3, **kw)
    env.reset(seed=0)
    a = np.zeros(3, dtype=np.float32)
    for k in range(1, steps + 1):
        _, _, term, trunc, info = env.step(a)
        assert not term and trunc == (k == steps)
        assert ("episode_metrics" in info) == (k == steps)
    assert info["time"] == pytest.approx(steps * env.unwrapped.config.dt)


def test_shorter_episode_than_time_limit_truncates_at_episode_s():
    env = gym.make(S4, episode_s=30.0, max_distance_m=1e3)  # TimeLimit 1200, env 600 steps
    env.reset(seed=0)
    a = np.zeros(3, dtype=np.float32)
    for k in range(1, 601):
        _, _, term, trunc, info = env.step(a)
        assert not term and trunc == (k == 600)
    assert "episode_metrics" in info


def test_matching_max_episode_steps_truncates_there():
    env = gym.make(S4, episode_s=30.0, max_episode_steps=600, max_distance_m=1e3)
    env.reset(seed=0)
    a = np.zeros(3, dtype=np.float32)
    for k in range(1, 601):
        _, _, term, trunc, info = env.step(a)
        assert not term
        assert trunc == (k == 600)
    assert info["time"] == pytest.approx(30.0)
    assert "episode_metrics" in info


# --- episode end, reward, metrics -------------------------------------------------------

def test_truncation_reward_and_episode_metrics():
    env = gym.make(S4, max_distance_m=1e3)
    assert env.unwrapped.config.effort_weight == 0.0
    env.reset(seed=21)
    actions = np.random.default_rng(3).uniform(-1, 1, (N_STEPS, 3)).astype(np.float32)
    errs = []
    for k, a in enumerate(actions, start=1):
        _, r, term, trunc, info = env.step(a)
        errs.append(info["tracking_error"])
        assert r == -info["tracking_error"]
        assert info["time"] == pytest.approx(k * DT)
        assert not term
        assert trunc == (k == N_STEPS)
        assert ("episode_metrics" in info) == (k == N_STEPS)
        # tracking error = distance from the follower to the true reference in info
        assert info["tracking_error"] == pytest.approx(
            math.hypot(*(info["follower_pose"][:2] - info["true_reference"][:2])), abs=1e-12)
    times = DT * np.arange(1, N_STEPS + 1)
    exp = tracking_metrics(np.array(errs), times, steady_start=10.0)
    got = info["episode_metrics"]
    assert got.keys() == exp.keys()
    for key in exp:
        assert got[key] == pytest.approx(exp[key], rel=1e-12), key
    # the steady window has the 1001 samples at t = 10.00 ... 60.00 s
    steady = np.array(errs[199:])
    assert got["steady_mean"] == pytest.approx(steady.mean(), rel=1e-12)
    assert got["steady_max"] == steady.max()


def test_true_reference_is_p_d_behind_the_true_target():
    env = gym.make(S4)
    env.reset(seed=1)
    for _ in range(50):
        _, _, _, _, info = env.step(np.zeros(3, dtype=np.float32))
    x, y, psi = info["true_target"][:3]
    pdx, pdy = -0.65, 0.12  # eq. (63), surge sign restored
    xr = x + math.cos(psi) * pdx - math.sin(psi) * pdy
    yr = y + math.sin(psi) * pdx + math.cos(psi) * pdy
    np.testing.assert_allclose(info["true_reference"], [xr, yr, psi], atol=1e-12)


def test_effort_weight_in_reward():
    w = 0.5
    env = gym.make(S4, effort_weight=w)
    env.reset(seed=0)
    a = np.array([0.5, -2.0, 0.1], dtype=np.float64)  # -2 is clipped to -1 for the cost too
    _, r, _, _, info = env.step(a)
    assert r == pytest.approx(-info["tracking_error"] - w * (0.25 + 1.0 + 0.01) / 3.0, abs=1e-12)


def test_termination_when_far_with_penalty():
    maxd = 3.0
    env = gym.make(S4, max_distance_m=maxd)
    env.reset(seed=0)
    a = np.zeros(3, dtype=np.float32)
    for k in range(1, N_STEPS + 1):
        _, r, term, trunc, info = env.step(a)
        assert not trunc and info["time"] == pytest.approx(k * DT)
        if term:
            break
        assert info["tracking_error"] <= maxd
        assert r == -info["tracking_error"]
    assert term, "a follower with zero thrust must fall behind a 0.52 m/s target"
    assert 1 < k < 200  # starts ~1.9 m away, target pulls away at ~0.5 m/s
    assert info["tracking_error"] > maxd
    assert r == pytest.approx(-info["tracking_error"] - maxd * (N_STEPS - k), rel=1e-12)
    m = info["episode_metrics"]
    assert m["full_max"] == pytest.approx(info["tracking_error"])
    assert math.isnan(m["steady_mean"])  # ended before t = 10 s


def test_termination_at_first_step_when_max_distance_small():
    env = gym.make(S4, max_distance_m=1.0)
    env.reset(seed=0)
    _, r, term, _, info = env.step(np.zeros(3, dtype=np.float32))
    assert term
    assert r == pytest.approx(-info["tracking_error"] - 1.0 * (N_STEPS - 1), rel=1e-12)


# --- observation content ----------------------------------------------------------------

def test_observation_layout():
    env = gym.make(S4)
    assert env.observation_space.shape == (OBS_DIM,) == (16,)
    assert env.observation_space.dtype == np.float32
    assert env.action_space.shape == (3,)
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset(seed=0)
    d = decode(obs)
    assert list(d) == [f.name for f in OBS_FIELDS]
    assert len(d) == 16 and "target_u" in d and "ref_dx" in d
    assert d["cos_psi"] ** 2 + d["sin_psi"] ** 2 == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError):
        decode(np.zeros(15))
    batch = decode(np.zeros((4, 16)))
    assert batch["u"].shape == (4,)
    assert set(info) == {"tracking_error", "time", "true_target", "true_reference", "follower_pose"}


def test_observation_is_delayed_truth_and_measured_current():
    """obs(k) = f(target truth at k - D, follower at k, current at k): nothing present leaks."""
    env = gym.make(S4)
    D = env.unwrapped.task_spec.delay_steps
    obs, info = env.reset(seed=8)
    rng = np.random.default_rng(1)
    O, TT, P = [obs], [info["true_target"].copy()], [info["follower_pose"].copy()]
    for _ in range(2 * D + 5):
        obs, _, _, _, info = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
        O.append(obs)
        TT.append(info["true_target"].copy())
        P.append(info["follower_pose"].copy())
    p = env.unwrapped._sim.params[0]
    pdx, pdy = env.unwrapped.task_spec.p_d
    for k in range(D, len(O)):
        x, y, psi = P[k]
        xt, yt, pst, ut, vt, rt = TT[k - D]
        c, s = math.cos(psi), math.sin(psi)
        t = k * DT
        cx = p[dyn.P_CX] + p[dyn.P_CX + 1] * math.sin(p[dyn.P_CX + 2] * t + p[dyn.P_CX + 3])
        cy = p[dyn.P_CY] + p[dyn.P_CY + 1] * math.sin(p[dyn.P_CY + 2] * t + p[dyn.P_CY + 3])
        rx = xt + math.cos(pst) * pdx - math.sin(pst) * pdy - x
        ry = yt + math.sin(pst) * pdx + math.cos(pst) * pdy - y
        exp = {"cos_psi": c, "sin_psi": s,
               "target_dx": c * (xt - x) + s * (yt - y), "target_dy": -s * (xt - x) + c * (yt - y),
               "target_cos_dpsi": math.cos(pst - psi), "target_sin_dpsi": math.sin(pst - psi),
               "target_u": ut, "target_v": vt, "target_r": rt,
               "ref_dx": c * rx + s * ry, "ref_dy": -s * rx + c * ry,
               "current_u": c * cx + s * cy, "current_v": -s * cx + c * cy}
        d = decode(O[k])
        for name, val in exp.items():
            assert d[name] == pytest.approx(val, rel=1e-6, abs=2e-6), (k, name)


def test_zero_delay_observes_the_present_target():
    env = gym.make(S4, delay_s=0.0)
    assert env.unwrapped.task_spec.delay_steps == 0
    obs, info = env.reset(seed=0)
    for _ in range(30):
        obs, _, _, _, info = env.step(np.array([0.3, 0.0, 0.0], dtype=np.float32))
    x, y, psi = info["follower_pose"]
    xt, yt = info["true_target"][:2]
    assert obs[OBS_INDEX["target_dx"]] == pytest.approx(math.cos(psi) * (xt - x) + math.sin(psi) * (yt - y),
                                                        abs=2e-6)
    assert obs[OBS_INDEX["target_u"]] == pytest.approx(info["true_target"][3], abs=1e-6)


def test_returned_arrays_are_copies():
    env = gym.make(S4)
    obs, info = env.reset(seed=0)
    obs2, _, _, _, info2 = env.step(np.zeros(3, dtype=np.float32))
    snap = _sim_snapshot(env)
    for arr in (obs, obs2, info["true_target"], info2["true_target"], info2["follower_pose"],
                info2["true_reference"]):
        arr[...] = 1e9
    _assert_same_snapshot(snap, _sim_snapshot(env))


# --- rendering ----------------------------------------------------------------------------

def test_render_rgb_array(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = gym.make(S4, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(20):
        env.step(env.action_space.sample())
    frame = env.render()
    assert isinstance(frame, np.ndarray)
    assert frame.shape == (600, 600, 3) and frame.dtype == np.uint8
    assert frame.reshape(-1, 3).std(axis=0).max() > 1.0  # not uniform
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 3  # background, target, follower, ...
    env.close()


def test_render_without_mode_warns_and_returns_none():
    env = AUVFollowEnv()
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None


def test_render_human_headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = gym.make(S4, render_mode="human")
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros(3, dtype=np.float32))
    assert env.render() is None
    env.close()


def test_record_video(tmp_path, monkeypatch):
    pytest.importorskip("moviepy")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(gym.make(S4, render_mode="rgb_array"), str(tmp_path), episode_trigger=lambda e: True)
    env.reset(seed=0)
    for _ in range(40):
        env.step(env.action_space.sample())
    env.close()
    assert list(tmp_path.glob("*.mp4"))


# --- vectorisation ----------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["sync", "async"])
def test_make_vec(mode):
    n = 4
    venv = gym.make_vec(S4, num_envs=n, vectorization_mode=mode)
    try:
        obs, info = venv.reset(seed=10)
        assert obs.shape == (n, 16) and obs.dtype == np.float32
        # env i is seeded with 10 + i: the same as a single env
        for i in range(n):
            single = gym.make(S4)
            o, _ = single.reset(seed=10 + i)
            np.testing.assert_array_equal(obs[i], o)
        for _ in range(5):
            obs, rew, term, trunc, info = venv.step(venv.action_space.sample())
        assert obs.shape == (n, 16) and rew.shape == (n,) and term.shape == (n,)
        assert np.all(np.isfinite(obs)) and np.all(rew < 0)
    finally:
        venv.close()


def test_sb3_subproc_vec_env():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = make_vec_env(S4, n_envs=2, seed=0, vec_env_cls=SubprocVecEnv,
                        vec_env_kwargs={"start_method": "fork"})
    try:
        obs = venv.reset()
        assert obs.shape == (2, 16)
        for _ in range(5):
            obs, rew, done, info = venv.step(np.random.default_rng(0).uniform(-1, 1, (2, 3)))
        assert obs.shape == (2, 16) and rew.shape == (2,) and not done.any()
        assert "tracking_error" in info[0]
    finally:
        venv.close()
