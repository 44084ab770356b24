"""The Leader tiers' target: hidden semi-Markov manoeuvre modes and outlier fixes, defined once
in the kernel (auv_follow_env/dynamics.py, "leader targets"). Expectations are the generator's
definition worked out by hand: Gamma(4) durations about the drawn means, the chain's jump
probabilities, the stationary start's time shares, survey legs within +- 5 % of the leg length,
U-turns of pi, and the outliers' share."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from auv_follow_env import dynamics as dyn
from auv_follow_env.params import Condition, make_config
from auv_follow_env.sim import link_row

DT = 0.05


def _rows(n: int, **kw) -> np.ndarray:
    c = Condition(update_period_s=1.0, target_speed=0.0, target_yaw_rate_max=1.0, **kw)
    return link_row(np.zeros((n, dyn.NP)), c, DT, make_config("S4").nominal)


def _runs(mode: np.ndarray, prog: np.ndarray):
    """Completed runs of each env's mode sequence (the first, length-biased one excluded):
    (mode, length in steps, final progress, next mode) per run."""
    out = []
    for i in range(mode.shape[1]):
        m = mode[:, i]
        ch = np.flatnonzero(m[1:] != m[:-1]) + 1  # index of the first step of each new mode
        for a, b in zip(ch[:-1], ch[1:], strict=True):
            out.append((int(m[a]), b - a, prog[b - 1, i], int(m[b])))
    return out


def test_wander_durations_are_gamma4_about_the_drawn_means_and_the_chain_jumps_as_defined():
    """Modes 2 (cruise, turns, loiter, sprint), means 8 / 4 / 6 / 3 s: the completed durations'
    mean is the drawn mean within 3 % (standard error 0.5 / sqrt(n)) and their coefficient of
    variation 1 / sqrt(4) = 0.5 within 0.03; cruise is left for left / right / loiter / sprint
    with probabilities 0.3 / 0.3 / 0.2 / 0.2, and every other mode returns to cruise."""
    means = {dyn.LD_CRUISE: 8.0, dyn.LD_TURN_L: 4.0, dyn.LD_TURN_R: 4.0, dyn.LD_LOITER: 6.0, dyn.LD_SPRINT: 3.0}
    p = _rows(400, leader_modes=2.0, leader_cruise_mean_s=8.0, leader_turn_mean_s=4.0, leader_loiter_mean_s=6.0,
              leader_sprint_mean_s=3.0)
    tr = dyn.leader_trace(p, np.arange(1, 401, dtype=np.int64) * 7919, 6000)
    runs = _runs(tr[:, :, 0], tr[:, :, 1])
    for mode, mean in means.items():
        d = np.array([length for m, length, _, _ in runs if m == mode]) * DT
        assert len(d) > 800
        assert abs(d.mean() / mean - 1.0) < 0.03, (mode, d.mean())
        assert abs(d.std() / d.mean() - 0.5) < 0.03, (mode, d.std() / d.mean())
    nxt = np.array([n for m, _, _, n in runs if m == dyn.LD_CRUISE])
    for mode, share in ((dyn.LD_TURN_L, 0.3), (dyn.LD_TURN_R, 0.3), (dyn.LD_LOITER, 0.2), (dyn.LD_SPRINT, 0.2)):
        assert abs(np.mean(nxt == mode) - share) < 4 * math.sqrt(share * (1 - share) / len(nxt))
    assert all(n == dyn.LD_CRUISE for m, _, _, n in runs if m != dyn.LD_CRUISE)


def test_modes_one_has_no_speed_modes_and_turns_at_the_drawn_rate():
    """Modes 1: only cruise and turns (left and right equally often); once the lag has settled a
    turn's rate is the drawn rate (wobble off: exactly, up to the lag's remainder)."""
    p = _rows(100, leader_modes=1.0, leader_turn_rate=0.12, leader_turn_mean_s=20.0, leader_wobble_rate=0.0,
              leader_wobble_speed=0.0)
    tr = dyn.leader_trace(p, np.arange(1, 101, dtype=np.int64), 4000)
    mode, r = tr[:, :, 0], tr[:, :, 3]
    assert set(np.unique(mode)) == {dyn.LD_CRUISE, dyn.LD_TURN_L, dyn.LD_TURN_R}
    # 10 s (10 lag time constants) into a turn: +-0.12 rad/s within 0.24 e^-10 (the lag may start
    # from the opposite turn's rate if the cruise between was short)
    settled = np.zeros_like(mode, dtype=bool)
    for i in range(mode.shape[1]):
        run = 0
        for k in range(mode.shape[0]):
            run = run + 1 if k and mode[k, i] == mode[k - 1, i] else 0
            settled[k, i] = run >= 200
    left = settled & (mode == dyn.LD_TURN_L)
    right = settled & (mode == dyn.LD_TURN_R)
    assert left.sum() > 1000 and right.sum() > 1000
    np.testing.assert_allclose(r[left], 0.12, atol=0.24 * math.exp(-10) + 1e-12)
    np.testing.assert_allclose(r[right], -0.12, atol=0.24 * math.exp(-10) + 1e-12)


def test_the_start_is_stationary_mode_shares_are_time_shares():
    """At t = 0 the modes are drawn by their share of time: visits (cruise 1/2, each turn 0.15,
    loiter and sprint 0.1 each) times mean durations (10, 5, 5, 8, 4 s), normalised."""
    n = 20000
    p = _rows(n, leader_modes=2.0, leader_cruise_mean_s=10.0, leader_turn_mean_s=5.0, leader_loiter_mean_s=8.0,
              leader_sprint_mean_s=4.0)
    tr = dyn.leader_trace(p, np.arange(n, dtype=np.int64) + 11, 0)
    w = np.array([0.5 * 10, 0.15 * 5, 0.15 * 5, 0.1 * 8, 0.1 * 4])
    share = w / w.sum()
    for mode in range(5):
        got = np.mean(tr[0, :, 0] == mode)
        assert abs(got - share[mode]) < 4 * math.sqrt(share[mode] * (1 - share[mode]) / n), (mode, got)


def test_survey_legs_are_the_leg_length_within_5_percent_and_uturns_turn_pi_alternately():
    """A survey (share 1): legs end after the drawn length times 1 + U(-0.05, 0.05) of distance
    (one step of overshoot at most); each U-turn plus the lag's tail turns the heading by pi
    (wobble off), alternately left and right."""
    L, w, T = 12.0, 0.3, 1.0
    p = _rows(40, leader_modes=1.0, leader_survey_share=1.0, leader_leg_m=L, leader_uturn_rate=w,
              leader_rate_lag_s=T, leader_wobble_speed=0.0, leader_wobble_rate=0.0)
    tr = dyn.leader_trace(p, np.arange(40, dtype=np.int64) + 3, 6000)
    mode, prog, r = tr[:, :, 0], tr[:, :, 1], tr[:, :, 3]
    assert set(np.unique(mode)) == {dyn.LD_LEG, dyn.LD_UTURN}
    legs = [(length, pr) for m, length, pr, _ in _runs(mode, prog) if m == dyn.LD_LEG]
    assert len(legs) > 200
    prog_end = np.array([pr for _, pr in legs])
    assert prog_end.min() >= 0.95 * L - 0.6 * DT and prog_end.max() <= 1.05 * L + 0.6 * DT
    assert prog_end.max() - prog_end.min() > 0.08 * L  # the jitter is drawn, not fixed
    turns = []
    for i in range(mode.shape[1]):
        m = mode[:, i]
        starts = np.flatnonzero((m[1:] == dyn.LD_UTURN) & (m[:-1] == dyn.LD_LEG)) + 1
        for a in starts[1:-1]:
            b = a + int(10 * T / DT) + int(math.pi / w / DT) + 200  # well past the lag's tail
            if b < len(m) and np.all(m[a:a + int(math.pi / w / DT) // 2] == dyn.LD_UTURN):
                turns.append(DT * r[a - 1:b, i].sum())  # rates held over steps a .. b
    turns = np.array(turns)
    assert len(turns) > 50
    # the leg after a U-turn turns nothing once the lag has settled, so the sum is the U-turn's heading change
    np.testing.assert_allclose(np.abs(turns), math.pi, atol=0.03)
    assert 0.3 < np.mean(turns > 0) < 0.7


def test_leader_tiers_are_registered_with_their_own_test_seeds_and_refuse_test_seeds_for_training():
    from auv_follow_env import ENV_IDS_LEADER, ENV_IDS_V1, LEADER_TIERS, TIERS, check_training_seeds

    assert ENV_IDS_LEADER == ("AUVFollow-Leader-Easy-v1", "AUVFollow-Leader-Medium-v1", "AUVFollow-Leader-Hard-v1")
    assert set(ENV_IDS_LEADER) <= set(ENV_IDS_V1)  # v1 ids: the CLI, the seed checks and warm-up take them
    seeds = [s for t in {**TIERS, **LEADER_TIERS}.values() for s in t.test_seeds]
    assert len(seeds) == len(set(seeds)) == 700
    for t in LEADER_TIERS.values():
        assert len(t.test_seeds) == 100 and min(t.test_seeds) >= 1_000_000
        with pytest.raises(ValueError, match="reserved for the tiers' test sets"):
            check_training_seeds([t.test_seeds[0]])
        base = TIERS[t.name.split("-")[1]]  # the link of the v1 tier of the same level
        for k in ("update_period_s", "latency_s", "loss_prob", "fix_sigma_m"):
            assert t.ranges[k] == base.ranges[k]
    env = gym.make("AUVFollow-Leader-Hard-v1")
    _, info = env.reset(seed=1)
    c = info["condition"]
    assert c["leader_modes"] == 2.0 and 0.25 <= c["leader_uturn_rate"] <= 0.40 and 0.05 <= c["outlier_share"] <= 0.15


def test_a_leader_needs_the_ou_target_off_and_bounds_that_let_it_manoeuvre():
    with pytest.raises(ValueError, match="target_speed_std"):
        gym.make("AUVFollow-v1", leader_modes=1, target_speed_std=0.1)
    with pytest.raises(ValueError, match="target_yaw_rate_max"):
        gym.make("AUVFollow-v1", leader_modes=1, leader_turn_rate=0.3, target_yaw_rate_max=0.2)
    env = gym.make("AUVFollow-v1", leader_modes=1)  # the scenario's tones are switched off for a leader
    _, info = env.reset(seed=0)
    assert info["condition"]["target_surge_amp"] == 0.0 and info["condition"]["target_speed"] == 0.0
    with pytest.raises(ValueError, match="leader_modes"):
        gym.make("AUVFollow-v1", leader_modes=1.5)


def test_the_target_follows_the_leader_and_v1_targets_are_untouched():
    """On a Leader tier the true target's speed and turn rate are the leader's (the tones' base
    speed is zeroed); AUVFollow-Hard-v1's target still has its OU speed about target_speed."""
    env = gym.make("AUVFollow-Leader-Easy-v1")
    env.reset(seed=3)
    u, r = [], []
    for _ in range(400):
        _, _, term, trunc, info = env.step(np.zeros(3))
        u.append(info["true_target"][3])
        r.append(info["true_target"][5])
        if term or trunc:
            break
    assert 0.3 < np.median(u) < 0.7 and np.max(np.abs(r)) <= 0.5
    assert dyn.P_LD_MODES < dyn.NP and dyn.R_LD_WR < dyn.NR


def test_outlier_fixes_come_at_the_set_share_with_student_t_errors():
    """With exact fixes (no noise) every fix equals the target's measured position except the
    outliers: the share of fixes off by more than 1 mm is the outlier share (binomial bounds), and
    their errors are heavy-tailed (a 2-D Student-t with 3 dof, scale 0.5 m: median radius
    0.5 * sqrt(2 F(2, 3) median) = 0.5 * sqrt(2 * 0.881) = 0.664 m)."""
    from auv_follow_env.layout import OBS_INDEX_V1 as IX

    share, scale = 0.3, 0.5
    env = gym.make("AUVFollow-v1", leader_modes=1, outlier_share=share, outlier_scale_m=scale,
                   update_period_s=0.05, latency_s=0.0, target_yaw_rate_max=1.0, max_episode_steps=None)
    off = []
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        for _ in range(1000):
            obs, _, term, trunc, info = env.step(np.zeros(3))
            fol, tgt = info["follower_pose"], info["true_target"]
            c, s = math.cos(fol[2]), math.sin(fol[2])
            dx, dy = tgt[0] - fol[0], tgt[1] - fol[1]
            # the fix sent this step (latency 0: it arrives now), in the follower's body frame
            off.append(math.hypot(obs[IX["target_dx"]] - (c * dx + s * dy), obs[IX["target_dy"]] - (-s * dx + c * dy)))
            if term or trunc:
                break
    off = np.array(off)
    n = len(off)
    got = np.mean(off > 1e-3)
    assert abs(got - share) < 4 * math.sqrt(share * (1 - share) / n), got
    assert abs(np.median(off[off > 1e-3]) / 0.664 - 1.0) < 0.15


def test_the_particle_filters_generator_is_the_kernels():
    """The model-aware filter carries its own copy of the generator (per-particle draws); run
    from the same settings, its mode durations and jump shares match the kernel's leader_trace
    within sampling error (means 8 / 4 / 6 / 3 s; jumps from cruise 0.3 / 0.3 / 0.2 / 0.2)."""
    from controllers import _leader_pf as pf

    fields = dict(leader_modes=2.0, leader_cruise_mean_s=8.0, leader_turn_mean_s=4.0, leader_loiter_mean_s=6.0,
                  leader_sprint_mean_s=3.0)
    cfg, prior = pf.pf_config(make_config("S4").task_spec(), fields=fields)
    tr = pf.particle_trace(cfg, prior, 300, 6000, 7)
    kern = dyn.leader_trace(_rows(300, **fields), np.arange(1, 301, dtype=np.int64), 6000)
    for got in (tr, kern):
        runs = _runs(got[:, :, 0], np.zeros_like(got[:, :, 0]))
        for mode, mean in ((dyn.LD_CRUISE, 8.0), (dyn.LD_TURN_L, 4.0), (dyn.LD_LOITER, 6.0), (dyn.LD_SPRINT, 3.0)):
            d = np.array([length for m, length, _, _ in runs if m == mode]) * DT
            assert abs(d.mean() / mean - 1.0) < 0.04, (mode, d.mean())
        nxt = np.array([n for m, _, _, n in runs if m == dyn.LD_CRUISE])
        assert abs(np.mean(nxt == dyn.LD_LOITER) - 0.2) < 0.03
    # the speeds and rates held: the same law (cruise 0.5 m/s by default, turns at +-0.15 rad/s)
    for got, col in ((tr, 1), (kern, 2)):
        cruise = got[200:, :, 0] == dyn.LD_CRUISE
        assert abs(np.median(got[200:, :, col][cruise]) - 0.5) < 0.02
