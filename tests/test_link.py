"""The v1 acoustic link, random target, current and thrusters against independent expectations.

Every expected value is derived by hand from the documented model, never printed by the code
under test:

* i.i.d. loss p: the lost count of n packets is Binomial(n, p) -> 99.9 % interval
  p +- 3.29 sqrt(p (1 - p) / n);
* Gilbert-Elliott with loss 1 in the bad state and 0 in the good one: a loss burst is a stay
  in the bad state, geometric with mean 1 / p_bad->good; the stationary loss fraction is
  p_gb / (p_gb + p_bg);
* constant latency L and period P (multiples of dt): the age at step k cycles through
  L, L + dt, ..., L + P - dt, so its mean is L + (P - dt) / 2 (the continuous-time
  "latency + period / 2" on the control grid);
* stationary OU with std s and correlation time T: Var = s^2, corr(lag) = exp(-lag / T);
* fix noise: per-axis position sigma = sigma_0 + k * range;
* thruster lag T from rest under a constant command F: F (1 - exp(-n dt / T)) after n steps;
  rate limit r: the force ramps by r * F_max * dt per step.
"""

from __future__ import annotations

import math
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from numba import njit

import auv_follow_env  # noqa: F401
from auv_follow_env import dynamics as dyn
from auv_follow_env.layout import OBS_DIM_V1, OBS_INDEX_V1
from auv_follow_env.params import make_config
from auv_follow_env.tiers import TIER_NAMES, TIERS, TRAIN_SEED_LIMIT, check_training_seeds, make_tier_config
from controllers import make_controller

V1 = "AUVFollow-v1"
#: a still target, no current, no disturbances: the follower stays put under zero action
STILL = dict(scenario="S1", disturbance="L0", target_speed=0.0, target_surge_amp=0.0,
             target_yaw_rate_amp=0.0, max_distance_m=1e4)
AGE, SINCE, NEW, HAS = (OBS_INDEX_V1[k] for k in ("packet_age", "since_arrival", "new_packet", "has_packet"))


def _run_vec(n_envs: int, n_steps: int, seed: int = 0, env_id: str = V1, **kw):
    """Zero-action rollout of a native vector env: obs (T + 1, N, 20), infos, the env."""
    env = gym.make_vec(env_id, num_envs=n_envs, **kw)
    obs, info = env.reset(seed=seed)
    out, infos = [obs], [info]
    a = np.zeros((n_envs, 3), dtype=np.float32)
    for _ in range(n_steps):
        obs, _, _, _, info = env.step(a)
        out.append(obs)
        infos.append(info)
    return np.array(out), infos, env


# --- the kernel's generator ----------------------------------------------------------------

def test_splitmix64_matches_the_reference_sequence():
    # reference: SplitMix64 from state 0 (Steele et al. 2014; the seeding generator of
    # xoshiro), first outputs computed with Python integers below
    def ref(state, n):
        out = []
        for _ in range(n):
            state = (state + 0x9E3779B97F4A7C15) % 2**64
            z = state
            z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) % 2**64
            z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) % 2**64
            out.append(z ^ (z >> 31))
        return out

    expected = ref(0, 5)
    assert expected[0] == 0xE220A8397B1DCDAF  # the published first output for seed 0
    rs = np.zeros(1, dtype=np.uint64)
    got = [int(dyn.next_u64(rs, 0)) for _ in range(5)]
    assert got == expected
    u = dyn.draw_uniforms(np.array([12345], dtype=np.uint64), 200_000)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert abs(u.mean() - 0.5) < 4 * math.sqrt(1 / 12 / u.size)
    z = dyn.draw_normals(np.array([7], dtype=np.uint64), np.zeros((1, dyn.NR)), 200_000)
    assert abs(z.mean()) < 4 / math.sqrt(z.size) and abs(z.var() - 1.0) < 4 * math.sqrt(2 / z.size)


@njit
def _scalar_processes(proc, rs, p, steps):
    for _ in range(steps):
        for i in range(proc.shape[0]):
            dyn.update_processes(proc, rs, p, i)


def _process_rows(n: int) -> np.ndarray:
    """Param rows where each env draws a different subset of the seven normals (0 to 7 per step,
    so the Box-Muller pairs' cached second value is used at every phase)."""
    rng = np.random.default_rng(5)
    p = np.zeros((n, dyn.NP))
    stds = (dyn.P_OUU_STD, dyn.P_OUR_STD, dyn.P_CS_STD, dyn.P_CD_STEP, dyn.P_DN, dyn.P_DN + 1, dyn.P_DN + 2)
    for i in range(n):
        on = [(i >> c) & 1 for c in range(7)]  # envs 0..127: every subset
        for c, col in enumerate(stds):
            p[i, col] = on[c] * rng.uniform(0.1, 1.0)
    for col in (dyn.P_OUU_A, dyn.P_OUR_A, dyn.P_CS_A, dyn.P_DN_A):
        p[:, col] = rng.uniform(0.5, 0.99, n)
    p[:, dyn.P_CS_MEAN] = 0.1
    return p


def test_block_processes_draw_what_the_per_env_reference_draws():
    """The step's block version of the random processes (SIMD logarithms and sines) against the
    per-env reference update_processes (scalar Box-Muller, libm): with libm the same bits, with the
    SIMD functions the same uniforms (the generators end in the same state) and normals within
    rounding."""
    n, steps = 150, 9
    p = _process_rows(n)
    rs0 = np.arange(1, n + 1, dtype=np.uint64) * np.uint64(7919)
    proc0 = np.zeros((n, dyn.NR))
    proc0[:, dyn.R_CDIR] = np.linspace(-3.0, 3.0, n)
    ref_proc, ref_rs = proc0.copy(), rs0.copy()
    _scalar_processes(ref_proc, ref_rs, p, steps)
    assert np.count_nonzero(ref_proc[:, dyn.R_GAUSS_HAS]) > 10  # the cache is exercised
    libm_proc, libm_rs = proc0.copy(), rs0.copy()
    dyn.update_processes_all(libm_proc, libm_rs, p, steps, False)
    np.testing.assert_array_equal(libm_proc, ref_proc)
    np.testing.assert_array_equal(libm_rs, ref_rs)
    simd_proc, simd_rs = proc0.copy(), rs0.copy()
    dyn.update_processes_all(simd_proc, simd_rs, p, steps, True)
    np.testing.assert_array_equal(simd_rs, ref_rs)
    np.testing.assert_array_equal(simd_proc[:, dyn.R_GAUSS_HAS], ref_proc[:, dyn.R_GAUSS_HAS])
    np.testing.assert_allclose(simd_proc, ref_proc, rtol=1e-13, atol=1e-15)
    assert not np.array_equal(simd_proc, ref_proc)  # a different computation, not libm again


def test_batched_v1_draws_equal_the_one_episode_reference():
    """The envs draw n episodes' parameters at once (sample_params_v1_many); the reference draws
    one episode through a validated Condition (sample_params_v1): the same rows bit for bit, the
    same kernel seeds, current directions and reported conditions, on every tier and with ranges
    over the fields whose columns need exp (correlation times, thruster lag) and the direction."""
    from auv_follow_env.sim import sample_params_v1, sample_params_v1_many

    configs = [make_tier_config(t) for t in TIER_NAMES] + [
        make_config("S2", version="v1", thruster_tc_s=(0.0, 0.5), current_direction_rad=(-1.0, 1.0),
                    latency_corr_s=(1.0, 5.0), target_speed_corr_s=(5.0, 30.0), disturbance_noise_r=(0.0, 0.02))]
    for config in configs:
        rows, seeds, directions, cond = sample_params_v1_many(config, [np.random.default_rng(s) for s in range(64)])
        for j in range(64):
            row, seed, direction, c = sample_params_v1(config, np.random.default_rng(j))
            np.testing.assert_array_equal(rows[j], row)
            assert (seeds[j], directions[j]) == (seed, direction)
            assert set(cond) == set(c)
            for key, v in c.items():
                got = cond[key][j] if isinstance(cond[key], np.ndarray) else cond[key]
                assert got == v, (key, got, v)


# --- loss ----------------------------------------------------------------------------------

def test_iid_loss_rate_is_binomial():
    p = 0.2
    _, infos, env = _run_vec(100, 1200, loss_prob=p, latency_s=0.0, **STILL)
    stats = infos[-1]["link_stats"]
    n, lost = stats["sent"].sum(), stats["lost"].sum()
    assert n >= 100_000
    half = 3.29 * math.sqrt(p * (1 - p) / n)
    assert abs(lost / n - p) < half, (lost / n, p, half)
    # with zero latency every packet that is not lost arrives on its own step
    assert (stats["arrived"] + stats["lost"] == stats["sent"]).all()


def test_gilbert_elliott_bursts_have_mean_length_one_over_p_bad_good():
    p_gb, p_bg = 0.05, 0.25
    obs, _, _ = _run_vec(100, 1200, latency_s=0.0, burst_p_good_bad=p_gb, burst_p_bad_good=p_bg,
                         burst_loss_bad=1.0, **STILL)
    new = obs[1:, :, NEW]  # 1 = this step's packet arrived (a packet every step, latency 0)
    lengths = []
    for e in range(new.shape[1]):
        run = 0
        for x in new[:, e]:
            if x == 0.0:
                run += 1
            elif run:
                lengths.append(run)
                run = 0
    lengths = np.array(lengths)
    assert lengths.size > 2000
    se = math.sqrt((1 - p_bg) / p_bg**2 / lengths.size)
    assert abs(lengths.mean() - 1 / p_bg) < 4 * se, (lengths.mean(), 1 / p_bg)
    frac = 1.0 - new.mean()
    assert abs(frac - p_gb / (p_gb + p_bg)) < 0.02


# --- latency and age -----------------------------------------------------------------------

@pytest.mark.parametrize("latency,period", [(1.0, 2.0), (0.5, 1.5), (2.0, 0.05)])
def test_mean_age_is_latency_plus_half_period_on_the_grid(latency, period):
    dt = 0.05
    obs, _, _ = _run_vec(2, 1200, latency_s=latency, update_period_s=period, **STILL)
    age = obs[:, :, AGE]
    n_p = round(period / dt)
    # a whole number of send cycles, after the warm-up filled the link
    age = age[: (age.shape[0] // n_p) * n_p]
    assert age.mean() == pytest.approx(latency + (period - dt) / 2, abs=1e-9)
    assert age.min() == pytest.approx(latency) and age.max() == pytest.approx(latency + period - dt)
    # since_arrival is the age minus the latency for a constant latency
    np.testing.assert_allclose(obs[:, :, SINCE], obs[:, :, AGE] - latency, atol=1e-5)


def test_out_of_order_packets_never_show():
    # a fast-varying Gauss-Markov latency with a large spread reorders packets constantly
    obs, infos, _ = _run_vec(20, 1200, latency_model="gauss_markov", latency_s=2.0, latency_spread_s=1.5,
                             latency_corr_s=0.3, update_period_s=0.2, **STILL)
    t = np.arange(obs.shape[0])[:, None] * 0.05
    meas_time = t - obs[:, :, AGE]
    has = obs[:, :, HAS] == 1.0
    d = np.diff(meas_time, axis=0)[has[1:] & has[:-1]]
    assert d.min() > -1e-5  # the measurement time of what is shown never goes back
    assert infos[-1]["link_stats"]["discarded"].sum() > 100  # and reordering did happen


def test_uniform_latency_stays_in_its_range():
    # a period longer than the largest latency: no reordering, so every packet is shown on
    # arrival and its age then is its latency rounded up to the grid
    obs, _, _ = _run_vec(50, 1200, latency_model="uniform", latency_s=1.0, latency_spread_s=0.5,
                         update_period_s=2.0, **STILL)
    new = obs[1:, :, NEW] == 1.0
    ages = obs[1:, :, AGE][new].astype(float)
    assert ages.min() >= 0.5 - 1e-6 and ages.max() <= 1.5 + 0.05 + 1e-6
    # uniform on [0.5, 1.5] rounded up to 0.05: mean 1.0 + 0.025, std sqrt(1/12) = 0.289
    assert ages.mean() == pytest.approx(1.025, abs=4 * 0.289 / math.sqrt(ages.size))
    assert ages.std() == pytest.approx(0.289, rel=0.1)


# --- fix noise -----------------------------------------------------------------------------

def test_position_noise_sigma_grows_with_range():
    s0, k = 0.05, 0.02
    env = gym.make_vec(V1, num_envs=200, latency_s=0.0, fix_sigma_m=s0, fix_sigma_per_m=k, init_offset_m=3.0,
                       **STILL)
    obs, info = env.reset(seed=1)
    errs, ranges = [], []
    for _ in range(50):
        obs, _, _, _, info = env.step(np.zeros((200, 3), dtype=np.float32))
        c, s = obs[:, 3].astype(float), obs[:, 4].astype(float)
        dx, dy = obs[:, 5].astype(float), obs[:, 6].astype(float)
        pose = info["follower_pose"]
        mx = pose[:, 0] + c * dx - s * dy  # measured target position, inertial
        my = pose[:, 1] + s * dx + c * dy
        tx, ty = info["true_target"][:, 0], info["true_target"][:, 1]
        errs.append(np.stack([mx - tx, my - ty], axis=1))
        ranges.append(np.hypot(tx - pose[:, 0], ty - pose[:, 1]))
    e = np.concatenate(errs)
    sigma = s0 + k * np.mean(ranges)
    assert np.std(e) == pytest.approx(sigma, rel=0.04)


# --- target and current processes ------------------------------------------------------------

def test_target_ou_variance_and_autocorrelation():
    std_u, T_u, std_r, T_r = 0.08, 5.0, 0.05, 3.0
    env = gym.make_vec(V1, num_envs=3000, latency_s=0.0, target_speed=1.0, target_surge_amp=0.0,
                       target_yaw_rate_amp=0.0, target_speed_std=std_u, target_speed_corr_s=T_u,
                       target_yaw_rate_std=std_r, target_yaw_rate_corr_s=T_r, target_speed_max=5.0,
                       target_yaw_rate_max=5.0, disturbance="L0", max_distance_m=1e4)
    _, info = env.reset(seed=3)
    a = np.zeros((3000, 3), dtype=np.float32)
    snaps = {0: info["true_target"].copy()}
    for k in range(1, 101):
        _, _, _, _, info = env.step(a)
        if k in (40, 100):
            snaps[k] = info["true_target"].copy()
    u0, u1 = snaps[0][:, 3], snaps[100][:, 3]
    r0, r1 = snaps[0][:, 5], snaps[40][:, 5]
    n = u0.size
    assert u0.mean() == pytest.approx(1.0, abs=4 * std_u / math.sqrt(n))
    assert u0.var() == pytest.approx(std_u**2, rel=4 * math.sqrt(2 / n))
    assert u1.var() == pytest.approx(std_u**2, rel=4 * math.sqrt(2 / n))  # stationary
    rho_u = math.exp(-5.0 / T_u)  # lag 100 steps = 5 s
    assert np.corrcoef(u0, u1)[0, 1] == pytest.approx(rho_u, abs=4 * (1 - rho_u**2) / math.sqrt(n))
    rho_r = math.exp(-2.0 / T_r)  # lag 40 steps = 2 s
    assert r0.var() == pytest.approx(std_r**2, rel=4 * math.sqrt(2 / n))
    assert np.corrcoef(r0, r1)[0, 1] == pytest.approx(rho_r, abs=4 * (1 - rho_r**2) / math.sqrt(n))


def test_target_speed_and_turn_rate_are_bounded():
    obs, infos, _ = _run_vec(50, 600, target_speed=0.5, target_speed_std=0.5, target_speed_min=0.2,
                             target_speed_max=0.8, target_yaw_rate_std=0.5, target_yaw_rate_max=0.1,
                             max_distance_m=1e4)
    u = np.array([i["true_target"][:, 3] for i in infos])
    r = np.array([i["true_target"][:, 5] for i in infos])
    assert u.min() >= 0.2 and u.max() <= 0.8 and np.abs(r).max() <= 0.1
    assert (u == 0.8).any() and (u == 0.2).any()  # the bounds are reached with std 0.5


def test_custom_and_gauss_markov_current_through_make():
    env = gym.make(V1, disturbance="L0", current_x=(0.1, 0.1), current_y=(-0.05, -0.05), current_speed=0.2,
                   current_direction_rad=math.pi / 2)
    obs, _ = env.reset(seed=0)
    c, s = obs[3], obs[4]
    cu, cv = obs[14], obs[15]
    vx, vy = c * cu - s * cv, s * cu + c * cv  # back to inertial
    assert vx == pytest.approx(0.1, abs=1e-6) and vy == pytest.approx(-0.05 + 0.2, abs=1e-6)


# --- thrusters -----------------------------------------------------------------------------

def test_thruster_lag_and_rate_limit():
    T, dt = 0.5, 0.05
    env = gym.make(V1, thruster_tc_s=T, **STILL)
    env.reset(seed=0)
    sim = env.unwrapped._sim
    for n in range(1, 21):
        env.step(np.array([1.0, -0.5, 0.0], dtype=np.float32))
        assert sim.proc[0, dyn.R_F] == pytest.approx(150.0 * (1 - math.exp(-n * dt / T)), rel=1e-12)
        assert sim.proc[0, dyn.R_F + 1] == pytest.approx(-75.0 * (1 - math.exp(-n * dt / T)), rel=1e-12)
    env = gym.make(V1, thruster_rate=2.0, **STILL)  # 2 x the limit per second: 15 N per step
    env.reset(seed=0)
    sim = env.unwrapped._sim
    for n in range(1, 12):
        env.step(np.array([1.0, 0.0, 1.0], dtype=np.float32))
        assert sim.proc[0, dyn.R_F] == pytest.approx(min(150.0, 15.0 * n), rel=1e-12)
        assert sim.proc[0, dyn.R_F + 2] == pytest.approx(min(30.0, 3.0 * n), rel=1e-12)


# --- v0 is one setting of the link ---------------------------------------------------------

@pytest.mark.parametrize("scenario", ["S1", "S4"])
def test_v1_configured_as_v0_reproduces_v0(scenario):
    tau = {"S1": 0.5, "S4": 2.0}[scenario]
    e0 = gym.make(f"AUVFollow-{scenario}-v0")
    e1 = gym.make(V1, scenario=scenario, update_period_s=0.05, latency_s=tau, warmup_s=tau)
    ctrl0 = make_controller("PROPOSED", e0.unwrapped.task_spec)
    ctrl1 = make_controller("PROPOSED", e0.unwrapped.task_spec)
    o0, i0 = e0.reset(seed=4)
    o1, i1 = e1.reset(seed=4)
    for _ in range(1200):
        np.testing.assert_array_equal(o1[:16], o0)
        np.testing.assert_array_equal(o1[16:], [tau, 0.0, 1.0, 1.0])
        np.testing.assert_array_equal(i1["follower_pose"], i0["follower_pose"])
        np.testing.assert_array_equal(i1["true_target"], i0["true_target"])
        a0, _ = ctrl0.predict(o0)
        a1, _ = ctrl1.predict(o1[:16])
        o0, r0, t0, tr0, i0 = e0.step(a0)
        o1, r1, t1, tr1, i1 = e1.step(a1)
        assert r0 == r1 and (t0, tr0) == (t1, tr1)
    assert tr0 and i1["episode_metrics"] == i0["episode_metrics"]


# --- tiers ---------------------------------------------------------------------------------

def test_tiers_publish_disjoint_test_seeds_above_the_training_limit():
    seen: set[int] = set()
    for t in TIERS.values():
        assert len(t.test_seeds) == 100 and len(set(t.test_seeds)) == 100
        assert min(t.test_seeds) >= TRAIN_SEED_LIMIT
        assert not seen & set(t.test_seeds)
        seen |= set(t.test_seeds)
    assert TIERS["Extreme"].out_of_distribution and not TIERS["Hard"].out_of_distribution
    assert check_training_seeds(range(5)) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="reserved for the tiers' test sets"):
        check_training_seeds([1, TIERS["Hard"].test_seeds[3]])
    with pytest.raises(ValueError, match="integers"):
        check_training_seeds([1.5])


@pytest.mark.parametrize("tier", TIER_NAMES)
def test_tier_draws_its_conditions_within_its_ranges(tier):
    t = TIERS[tier]
    env = gym.make_vec(t.env_id, num_envs=64)
    _, info = env.reset(seed=0)
    cond = info["condition"]
    for name, (lo, hi) in t.ranges.items():
        v = cond[name]
        assert (v >= lo).all() and (v <= hi).all(), name
        assert v.std() > 0.1 * (hi - lo) / math.sqrt(12), name  # actually drawn, not fixed
    for name, v in t.fixed.items():
        assert (cond[name] == v).all(), name
    # the drawn mismatch is the plant's damping
    p = env.unwrapped._sim.params if hasattr(env, "unwrapped") else env._sim.params
    np.testing.assert_allclose(p[:, dyn.P_XU], 15.0 * (1 + cond["mismatch"]))


@pytest.mark.parametrize("tier", TIER_NAMES)
def test_vector_env_equals_single_env_on_every_tier(tier):
    env_id = TIERS[tier].env_id
    n, steps, short = 3, 130, dict(episode_s=3.0, steady_start_s=1.0)
    vec = gym.make_vec(env_id, num_envs=n, max_episode_steps=60, **short)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, n, 3)).astype(np.float32)
    vobs, vinfo = vec.reset(seed=10)
    singles = [gym.make(env_id, **short) for _ in range(n)]
    sobs = [e.reset(seed=10 + i) for i, e in enumerate(singles)]
    conds = [s[1]["condition"] for s in sobs]
    assert len({c["latency_s"] for c in conds}) == n  # different conditions in one batch
    for i in range(n):
        np.testing.assert_array_equal(vobs[i], sobs[i][0])
        assert vinfo["condition"]["latency_s"][i] == conds[i]["latency_s"]
    pending = [False] * n
    for k in range(steps):
        vobs, vrew, vterm, vtrunc, vinfo = vec.step(actions[k])
        for i, e in enumerate(singles):
            if pending[i]:
                o, info = e.reset()
                pending[i] = False
                np.testing.assert_array_equal(vobs[i], o)
                assert vinfo["condition"]["loss_prob"][i] == info["condition"]["loss_prob"]
                continue
            o, r, te, tr, _ = e.step(actions[k, i])
            np.testing.assert_array_equal(vobs[i], o)
            assert vrew[i] == r and vterm[i] == te and vtrunc[i] == tr
            pending[i] = te or tr


def test_episodes_drawn_ahead_are_the_ones_each_env_would_draw():
    """The vector env draws each env's next episode ahead, several envs per call (BatchSim's
    draw_ahead); every env still plays its own generator's episodes in order, as a single env
    seeded alike does, also after some envs are reseeded (their draws made ahead are dropped)."""
    env_id, n, steps, kw = TIERS["Hard"].env_id, 24, 300, dict(max_distance_m=1.5)  # short episodes
    vec = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kw)
    singles = [gym.make(env_id, **kw) for _ in range(n)]
    vobs, _ = vec.reset(seed=100)
    for i, e in enumerate(singles):
        np.testing.assert_array_equal(vobs[i], e.reset(seed=100 + i)[0])
    actions = np.random.default_rng(1).uniform(-1, 1, (steps, n, 3)).astype(np.float32)
    pending, ends = [False] * n, 0
    for k in range(steps):
        if k == steps // 2:  # reseed the even envs
            mask = np.arange(n) % 2 == 0
            vobs, _ = vec.reset(seed=[500 + i if mask[i] else None for i in range(n)], options={"reset_mask": mask})
            for i in np.flatnonzero(mask):
                np.testing.assert_array_equal(vobs[i], singles[i].reset(seed=500 + i)[0])
                pending[i] = False
            continue
        vobs, vrew, vterm, vtrunc, _ = vec.step(actions[k])
        for i, e in enumerate(singles):
            if pending[i]:
                o, _ = e.reset()
                pending[i] = False
            else:
                o, r, te, tr, _ = e.step(actions[k, i])
                assert vrew[i] == r and vterm[i] == te and vtrunc[i] == tr
                pending[i] = te or tr
                ends += te or tr
            np.testing.assert_array_equal(vobs[i], o, err_msg=f"env {i} step {k}")
    assert ends > 5 * n  # many episodes per env, most of them drawn ahead


@pytest.mark.parametrize("env_id", [t.env_id for t in TIERS.values()] + [V1])
def test_check_env_gymnasium_and_sb3(env_id):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id)
    check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(gym.make(env_id), warn=True)
    assert env.observation_space.shape == (OBS_DIM_V1,)


@pytest.mark.parametrize("tier", TIER_NAMES)
def test_a_million_random_steps_stay_finite(tier):
    n = 1000
    env = gym.make_vec(TIERS[tier].env_id, num_envs=n)
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    for _ in range(1000):
        obs, rew, _, _, _ = env.step(rng.uniform(-1, 1, (n, 3)).astype(np.float32))
        assert np.isfinite(obs).all() and np.isfinite(rew).all()


_HASH_CODE = """
import hashlib, gymnasium as gym, numpy as np, auv_follow_env
env = gym.make("AUVFollow-Hard-v1")
h = hashlib.sha256()
obs, _ = env.reset(seed=7)
rng = np.random.default_rng(0)
for _ in range(400):
    h.update(obs.tobytes())
    obs, r, te, tr, _ = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
print(h.hexdigest())
"""


def test_seeded_episodes_are_identical_across_processes():
    import contextlib
    import io

    outs = {subprocess.run([sys.executable, "-c", _HASH_CODE], capture_output=True, text=True, timeout=300,
                           check=True).stdout.strip() for _ in range(2)}
    here = io.StringIO()
    with contextlib.redirect_stdout(here):
        exec(_HASH_CODE, {})  # the same episode in this process
    assert outs == {here.getvalue().strip()} and len(outs.pop()) == 64


def test_no_packet_yet_is_flagged_and_zeroed():
    env = gym.make(V1, latency_s=3.0, update_period_s=1.0, warmup_s=0.0, **STILL)
    obs, _ = env.reset(seed=0)
    assert obs[HAS] == 0.0 and obs[AGE] == 0.0 and (obs[5:14] == 0.0).all()
    for k in range(1, 61):
        obs, *_ = env.step(np.zeros(3, dtype=np.float32))
        if k < 60:  # the first packet (sent at t = 0) arrives at t = 3 s = step 60
            assert obs[HAS] == 0.0
    assert obs[HAS] == 1.0 and obs[NEW] == 1.0 and obs[AGE] == pytest.approx(3.0)


# --- bad input -----------------------------------------------------------------------------

@pytest.mark.parametrize("kw,name", [
    (dict(loss_prob=1.5), "loss_prob"),
    (dict(loss_prob=-0.1), "loss_prob"),
    (dict(update_period_s=0.0), "update_period_s"),
    (dict(update_period_s=0.01), "update_period_s"),
    (dict(update_period_s=(0.01, 1.0)), "update_period_s"),
    (dict(latency_model="lognormal"), "latency_model"),
    (dict(fix_sigma_m=-1.0), "fix_sigma_m"),
    (dict(latency_s="1.0"), "latency_s"),
    (dict(latency_s=float("nan")), "latency_s"),
    (dict(period_jitter_s=2.0, update_period_s=1.0), "period_jitter_s"),
    (dict(latency_model="uniform", latency_s=0.5, latency_spread_s=1.0), "latency_spread_s"),
    (dict(burst_p_bad_good=0.0), "burst_p_bad_good"),
    (dict(loss_prob=(0.3, 0.1)), "loss_prob"),
    (dict(loss_prob=(0.1, 1.3)), "loss_prob"),
    (dict(current_x=(0.2, 0.1)), "current_x"),
    (dict(current_x="ab"), "current_x"),
    (dict(thruster_tc_s=-1.0), "thruster_tc_s"),
    (dict(target_speed_min=1.0, target_speed_max=0.5), "target_speed_min"),
    (dict(warmup_s=1e6), "warmup_s"),
])
def test_bad_v1_parameters_are_refused_by_name(kw, name):
    with pytest.raises(ValueError, match=name):
        gym.make(V1, **kw)
    with pytest.raises(ValueError, match=name):
        gym.make("AUVFollow-Hard-v1", **kw)


def test_v1_parameters_on_v0_ids_say_where_they_exist():
    with pytest.raises(ValueError, match="only on the v1 ids"):
        gym.make("AUVFollow-S4-v0", loss_prob=0.1)
    with pytest.raises(ValueError, match="can be drawn per reset"):
        make_config("S4", version="v1", ranges={"dt": (0.01, 0.02)})


def test_overrides_fix_or_redraw_a_tier_field():
    env = gym.make_vec("AUVFollow-Hard-v1", num_envs=16, loss_prob=0.0, latency_s=(1.0, 1.1))
    _, info = env.reset(seed=0)
    assert (info["condition"]["loss_prob"] == 0.0).all()
    lat = info["condition"]["latency_s"]
    assert (lat >= 1.0).all() and (lat <= 1.1).all()
    # numpy scalars are numbers too
    gym.make("AUVFollow-Hard-v1", loss_prob=np.float32(0.1), fix_sigma_m=np.float64(0.02))


# --- docs ----------------------------------------------------------------------------------

def test_docs_tier_table_is_the_generated_one_and_snippets_run():
    from pathlib import Path

    from auv_follow_env.tiers import tier_summary_markdown

    root = Path(__file__).resolve().parents[1]
    for doc in ("docs/tiers.md",):  # the README links the tiers page instead of repeating the table
        page = (root / doc).read_text()
        block = page.split("<!-- tier-summary")[1].split("-->", 1)[1].split("<!-- /tier-summary -->")[0]
        assert block.strip() == tier_summary_markdown().strip(), doc
    text = (root / "docs" / "tiers.md").read_text()
    for code in text.split("```python")[1:]:
        code = code.split("```")[0]
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
