"""Replay of recorded link traces (``gym.make(id, link_trace=...)``) and ``auv-follow trace``.

Expected values are worked out from the trace's definition (docs/link_traces.md) and from the
env's ``info`` (the true target and the follower's pose), not from the replay code."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env.layout import OBS_INDEX_V1 as IX
from auv_follow_env.link_trace import LinkTrace, read_link_trace, record_link_trace
from controllers import make_controller

DT = 0.05
EPISODE_STEPS = 1200


def _episode(env, policy, seed, actions=None):
    """(observations, infos, actions) of one episode; ``actions`` given: played open loop."""
    obs, info = env.reset(seed=seed)
    if policy is not None:
        policy.reset()
    out_obs, infos, acts = [obs], [info], []
    for k in range(EPISODE_STEPS):
        a = actions[k] if actions is not None else policy.predict(obs)[0]
        obs, _, term, trunc, info = env.step(a)
        out_obs.append(obs)
        infos.append(info)
        acts.append(np.asarray(a))
        if term or trunc:
            break
    return np.array(out_obs), infos, np.array(acts)


def _body(dx, dy, psi):
    """A world-frame vector in the follower's body frame (x forward, y to port)."""
    c, s = math.cos(psi), math.sin(psi)
    return c * dx + s * dy, -s * dx + c * dy


def _trace(send, arrival, **noise):
    df = pd.DataFrame({"send_time": send, "arrival_time": arrival})
    for k, v in noise.items():
        df[k] = v
    return df


@pytest.mark.parametrize("env_id, kwargs, controller", [
    ("AUVFollow-Hard-v1", {}, "PROPOSED_KF_DOB"),
    ("AUVFollow-Leader-Hard-v1", {}, "PROPOSED_IMM_DOB"),
    # out-of-order arrivals: a Gauss-Markov latency wider than the period discards packets
    ("AUVFollow-v1", {"latency_model": "gauss_markov", "latency_s": 1.5, "latency_spread_s": 1.0,
                      "latency_corr_s": 0.5, "update_period_s": 0.5, "loss_prob": 0.2, "fix_sigma_m": 0.1}, "PID"),
])
def test_own_trace_replays_the_same_episode(env_id, kwargs, controller, tmp_path):
    env = gym.make(env_id, **kwargs)
    policy = make_controller(controller, env.unwrapped.task_spec)
    trace = record_link_trace(env, policy, seed=11)
    path = trace.write(tmp_path / "trace.csv")
    obs0, infos0, _ = _episode(gym.make(env_id, **kwargs), policy, 11)
    obs1, infos1, _ = _episode(gym.make(env_id, link_trace=path, **kwargs), policy, 11)
    np.testing.assert_array_equal(obs1, obs0)
    assert [i["tracking_error"] for i in infos1] == [i["tracking_error"] for i in infos0]
    assert infos1[-1]["link_stats"] == infos0[-1]["link_stats"]
    stats = infos0[-1]["link_stats"]
    assert stats["sent"] == len(trace) and stats["lost"] == int(trace.lost.sum())
    if env_id == "AUVFollow-v1":
        assert stats["discarded"] > 0  # (the case is the one it is meant to be)
    assert infos1[0]["link_trace"] == str(path)


def test_trace_file_round_trips_exactly(tmp_path):
    env = gym.make("AUVFollow-Medium-v1")
    trace = record_link_trace(env, make_controller("PID", env.unwrapped.task_spec), seed=2)
    for name in ("t.csv", "t.parquet"):
        back = read_link_trace(trace.write(tmp_path / name))
        np.testing.assert_array_equal(back.send_time, trace.send_time)
        np.testing.assert_array_equal(back.arrival_time, trace.arrival_time)  # (NaN = NaN for lost)
        np.testing.assert_array_equal(back.noise, trace.noise)


def test_instant_exact_link_shows_the_present_target():
    """A packet every step, arriving at once, without error: the follower sees the true target."""
    t = np.arange(EPISODE_STEPS + 1) * DT
    env = gym.make("AUVFollow-Hard-v1", link_trace=_trace(t, t))
    pid = make_controller("PID", env.unwrapped.task_spec)
    obs, infos, _ = _episode(env, pid, 5)
    for o, info in zip(obs[::37], infos[::37], strict=True):
        x, y, psi = info["follower_pose"]
        xt, yt, pt, ut, vt, rt = info["true_target"]
        dx, dy = _body(xt - x, yt - y, psi)
        assert o[IX["target_dx"]] == pytest.approx(dx, abs=1e-5)
        assert o[IX["target_dy"]] == pytest.approx(dy, abs=1e-5)
        assert o[IX["target_cos_dpsi"]] == pytest.approx(math.cos(pt - psi), abs=1e-6)
        assert o[IX["target_u"]] == pytest.approx(ut, abs=1e-6)
        assert o[IX["target_r"]] == pytest.approx(rt, abs=1e-6)
        # reference point p_t + R(psi_t) p_d, p_d = (-0.65, 0.12) m
        pd_x, pd_y = -0.65, 0.12
        rx = xt + math.cos(pt) * pd_x - math.sin(pt) * pd_y
        ry = yt + math.sin(pt) * pd_x + math.cos(pt) * pd_y
        bx, by = _body(rx - x, ry - y, psi)
        assert o[IX["ref_dx"]] == pytest.approx(bx, abs=1e-5)
        assert o[IX["ref_dy"]] == pytest.approx(by, abs=1e-5)
        assert (o[IX["packet_age"]], o[IX["since_arrival"]], o[IX["new_packet"]], o[IX["has_packet"]]) == (0, 0, 1, 1)


def test_latency_and_noise_as_recorded():
    """A packet every second, 2 s late, with a recorded error of (+0.5 m, -0.25 m): at time t >= 2 s the
    held packet was sent at floor(t - 2) s, so its age is t - floor(t - 2), and it shows the true target of
    that time plus the error."""
    send = np.arange(0.0, 61.0)
    env = gym.make("AUVFollow-Easy-v1", link_trace=_trace(send, send + 2.0, noise_x=0.5, noise_y=-0.25))
    pid = make_controller("PID", env.unwrapped.task_spec)
    obs, infos, _ = _episode(env, pid, 9)
    checked = 0
    for k in range(41, EPISODE_STEPS + 1, 13):
        t = k * DT
        sent_at = math.floor(t - 2.0 + 1e-9)
        assert obs[k][IX["packet_age"]] == pytest.approx(t - sent_at, abs=1e-5)
        assert obs[k][IX["since_arrival"]] == pytest.approx(t - (sent_at + 2.0), abs=1e-5)
        xt, yt = infos[round(sent_at / DT)]["true_target"][:2]
        x, y, psi = infos[k]["follower_pose"]
        dx, dy = _body(xt + 0.5 - x, yt - 0.25 - y, psi)
        assert obs[k][IX["target_dx"]] == pytest.approx(dx, abs=1e-5)
        assert obs[k][IX["target_dy"]] == pytest.approx(dy, abs=1e-5)
        assert obs[k][IX["new_packet"]] == (1.0 if abs(t - sent_at - 2.0) < 1e-9 else 0.0)
        checked += 1
    assert checked > 80
    # sends at 0-58 s arrive by 60 s, the episode's end
    assert infos[-1]["link_stats"] == {"sent": 61, "lost": 0, "arrived": 59, "discarded": 0, "overflow": 0}


def test_a_silent_link_leaves_the_warm_up_packets_only():
    """Every packet lost: after the packets in flight at t = 0 (the env's warm-up) nothing arrives."""
    send = np.arange(0.0, 60.0, 0.5)
    env = gym.make("AUVFollow-Medium-v1", link_trace=_trace(send, np.full(send.shape, np.nan)))
    pid = make_controller("PID", env.unwrapped.task_spec)
    obs, infos, _ = _episode(env, pid, 4)
    new = np.flatnonzero(obs[:, IX["new_packet"]] == 1.0)
    assert new.size == 0 or new.max() * DT < 10.0  # (Medium's latencies are seconds, not tens of seconds)
    age = obs[:, IX["packet_age"]]
    assert np.all(np.diff(age[new.max() + 1 if new.size else 0:]) == pytest.approx(DT, abs=1e-5))
    sent = int(np.sum(send <= infos[-1]["time"] + 1e-9))  # (blind, the follower may lose the target early)
    assert sent > 40
    assert infos[-1]["link_stats"] == {"sent": sent, "lost": sent, "arrived": 0, "discarded": 0, "overflow": 0}


def test_a_trace_changes_what_the_follower_hears_not_the_world():
    """Same seed, same actions: the target, the current and the follower move as without the trace."""
    actions = np.random.default_rng(0).uniform(-1, 1, (EPISODE_STEPS, 3))
    send = np.arange(0.0, 60.0, 3.0)
    edited = _trace(send, send + 0.2, noise_x=1.0)
    _, plain, _ = _episode(gym.make("AUVFollow-Hard-v1"), None, 21, actions)
    obs, traced, _ = _episode(gym.make("AUVFollow-Hard-v1", link_trace=edited), None, 21, actions)
    for key in ("true_target", "follower_pose", "true_reference"):
        np.testing.assert_array_equal(np.array([i[key] for i in traced]), np.array([i[key] for i in plain]))
    # the current (fields 14-15) is measured by the follower, not sent over the link
    _, plain_obs, _ = None, _episode(gym.make("AUVFollow-Hard-v1"), None, 21, actions)[0], None
    np.testing.assert_array_equal(obs[:, 14:16], plain_obs[:, 14:16])
    assert not np.array_equal(obs[:, 5:7], plain_obs[:, 5:7])


@pytest.mark.parametrize("df, words", [
    (pd.DataFrame({"send_time": [0.0, 1.0]}), "missing column(s) ['arrival_time']"),
    (pd.DataFrame({"send_time": [0.0], "arrival_time": [1.0], "latency": [1.0]}), "unknown column(s) ['latency']"),
    (_trace([0.0, -1.0], [1.0, 2.0]), "packet 1 (row 1): send_time=-1.0 is invalid"),
    (_trace([0.0, 2.0, 1.0], [1.0, 2.5, 3.0]), "packet 2 (row 2): send_time=1.0 is not after the previous"),
    (_trace([0.0, 1.0], [1.0, 0.5]), "packet 1 (row 1): arrival_time=0.5 is invalid"),
    (_trace([0.0, 1.0], [1.0, np.inf]), "arrival_time=inf is invalid"),
    (_trace([0.0, 1.0], [1.0, 2.0], lost=[0, 1]), "packet 1 (row 1): lost=1 contradicts arrival_time=2.0"),
    (_trace([0.0, 1.0], [1.0, 2.0], lost=[0, 2]), "lost=2 is invalid: 0 or 1"),
    (_trace([0.0, 1.0], [1.0, 2.0], noise_x=[0.0, np.nan]), "noise_x=nan is invalid"),
    (pd.DataFrame({"send_time": [], "arrival_time": []}), "has no packets"),
])
def test_malformed_trace_is_refused_naming_the_packet(df, words):
    with pytest.raises(ValueError) as err:
        gym.make("AUVFollow-Hard-v1", link_trace=df)
    assert words in str(err.value)


def test_csv_errors_name_the_line(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("send_time,arrival_time\n0.0,1.0\n1.0,abc\n")
    with pytest.raises(ValueError, match=r"packet 1 \(CSV line 3\): arrival_time='abc' is not a number"):
        gym.make("AUVFollow-Hard-v1", link_trace=p)
    with pytest.raises(ValueError, match="no such file"):
        gym.make("AUVFollow-Hard-v1", link_trace=tmp_path / "none.csv")
    with pytest.raises(ValueError, match="unknown suffix"):
        gym.make("AUVFollow-Hard-v1", link_trace=tmp_path / "log.txt")
    with pytest.raises(TypeError, match="link_trace=3 is a int"):
        gym.make("AUVFollow-Hard-v1", link_trace=3)


def test_two_packets_on_one_step_and_the_wrong_ids_are_refused():
    with pytest.raises(ValueError, match="packet 1 is sent at 0.04 s, on the same control step as packet 0"):
        gym.make("AUVFollow-Hard-v1", link_trace=_trace([0.01, 0.04], [1.0, 1.0]))
    with pytest.raises(ValueError, match="for the v1 ids"):
        gym.make("AUVFollow-S2-v0", link_trace=_trace([0.0], [1.0]))
    with pytest.raises(ValueError, match="not a vector-env keyword"):
        gym.make_vec("AUVFollow-Hard-v1", num_envs=2, vectorization_mode="vector_entry_point",
                     link_trace=_trace([0.0], [1.0]))


def test_cli_trace_writes_a_replayable_trace(tmp_path, capsys):
    from agents.cli import main

    out = tmp_path / "sub" / "trace.parquet"
    assert main(["trace", "--env", "AUVFollow-Easy-v1", "--seed", "3", "--out", str(out), "--policy", "PID"]) == 0
    printed = capsys.readouterr().out
    trace = read_link_trace(out)
    assert f"{len(trace)} packets" in printed and isinstance(trace, LinkTrace)
    pid = make_controller("PID", gym.make("AUVFollow-Easy-v1").unwrapped.task_spec)
    a, _, _ = _episode(gym.make("AUVFollow-Easy-v1"), pid, 3)
    b, _, _ = _episode(gym.make("AUVFollow-Easy-v1", link_trace=out), pid, 3)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(SystemExit) as exit_:
        main(["trace", "--env", "AUVFollow-Easy-v1", "--seed", "3", "--out", str(tmp_path / "t.txt")])
    assert exit_.value.code == 2 and "unknown suffix" in capsys.readouterr().err
