"""The single env's kernel (kernel_one.step_one on a packed one-env sim) against the batched
step_kernel, bit for bit: every array of the sim after every step (state, link queue, random
generator, caches, ...), over S1-S4 and the v1 tiers, sin/cos by SIMD (default) and libm, long episodes with
terminations and resets; and the env (packed path) against the vector env (step_kernel)."""

from __future__ import annotations

import gymnasium as gym
import numba
import numpy as np
import pytest

import auv_follow_env
from auv_follow_env import dynamics as dyn
from auv_follow_env.kernel_one import packed_arrays, step_one
from auv_follow_env.sim import BatchSim
from auv_follow_env.tiers import TIER_NAMES, make_env_config

ARRAYS = ("state", "k", "proc", "queue", "rs", "params", "cfg", "obs", "truth", "err_hist", "err_stage", "rew", "term")
IDX0 = np.zeros(1, dtype=np.int64)

CONFIGS = ([(f"S{i}", {}) for i in range(1, 5)]
           + [("S4", {"version": "v1", "tier": t}) for t in TIER_NAMES]
           + [("S2", {"version": "v1", "latency_model": "gauss_markov", "latency_s": 0.6, "latency_spread_s": 0.3,
                      "loss_prob": 0.2, "thruster_tc_s": 0.3, "max_distance_m": 4.0})])


def _pair(scenario: str, kw: dict, fast: bool) -> tuple[BatchSim, BatchSim]:
    config = make_env_config(scenario, **kw)
    sincos = "simd" if fast else "libm"
    return BatchSim(config, 1, sincos), BatchSim(config, 1, sincos, packed=True)


def _assert_same(a: BatchSim, b: BatchSim, where: str) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, f"{where}: {name}"
        assert np.array_equal(x.view(np.uint8), y.view(np.uint8)), f"{where}: {name}"  # the bits, NaNs too


def test_packed_arrays_are_views_with_the_usual_types():
    buf, arrays = packed_arrays(7, 20, 100)
    ref = BatchSim(make_env_config("S4", version="v1", tier="Hard"), 1)
    for name, arr in arrays.items():
        assert arr.base is not None and np.shares_memory(arr, buf), name
        assert arr.flags.c_contiguous and arr.flags.writeable and arr.flags.aligned, name
        assert arr.dtype == getattr(ref, name).dtype and arr.ndim == getattr(ref, name).ndim, name
    assert arrays["queue"].shape == (1, 7, dyn.NQ) and arrays["obs"].shape == (1, 20)
    assert arrays["err_hist"].shape == (1, 100) and arrays["err_hist"].ctypes.data % 64 == 0
    spans = sorted((a.ctypes.data, a.ctypes.data + a.nbytes) for a in arrays.values())
    assert all(e0 <= s1 for (_s0, e0), (s1, _e1) in zip(spans, spans[1:], strict=False))  # disjoint
    with pytest.raises(ValueError, match="observation length"):
        packed_arrays(3, 21, 10)


def test_packed_sim_has_the_kernel_types():
    a, b = _pair("S4", {}, False)
    for name in ARRAYS:
        assert numba.typeof(getattr(a, name)) == numba.typeof(getattr(b, name)), name
    with pytest.raises(ValueError, match="packed"):
        BatchSim(make_env_config("S4"), 2, packed=True)
    with pytest.raises(ValueError, match="packed=True"):
        a.step_one_call()


@pytest.mark.parametrize("fast", [False, True], ids=["libm", "simd"])
@pytest.mark.parametrize("scenario, kw", CONFIGS, ids=[kw.get("tier", "custom") if kw else s for s, kw in CONFIGS])
def test_step_one_equals_step_kernel_bit_for_bit(scenario, kw, fast):
    rng = np.random.default_rng(sum(map(ord, scenario + str(kw))) + fast)
    ends = resets = 0
    # a full episode and beyond (truncation), then episodes ending by termination (a tighter
    # max_distance_m) with resets from the same generators (the env's reset() without a seed)
    for seed, steps, extra in ((0, 1300, {}), (1, 600, {"max_distance_m": 4.0}), (2, 600, {"max_distance_m": 4.0})):
        a, b = _pair(scenario, {**kw, **extra}, fast)
        kernel, buf = b.step_one_call()
        ra, rb = np.random.default_rng(seed), np.random.default_rng(seed)
        a.reset(IDX0, [ra])
        b.reset(IDX0, [rb])
        _assert_same(a, b, f"reset {seed}")
        for t in range(steps):
            # random thrust, partly beyond [-1, 1], now and then biased to drive the follower away
            act = rng.uniform(-1.3, 1.3, 3) + (1.0 if t % 200 > 120 else 0.0)
            act = act.astype(np.float32) if t % 2 else act
            assert a.step(act) == -1
            bad, rew, term, k, err = kernel(buf, act)
            assert bad == -1
            where = f"seed {seed}, step {t}"
            _assert_same(a, b, where)
            assert rew == a.rew[0] and term == a.term[0] and k == a.k[0] and err == a.truth[0, dyn.T_ERR], where
            assert type(rew) is float and type(term) is bool and type(k) is int and type(err) is float
            if term or k == a.config.n_steps:
                ends += 1
                if extra and t % 4:  # (else one more step after the end)
                    a.reset(IDX0, [ra])
                    b.reset(IDX0, [rb])
                    resets += 1
                    _assert_same(a, b, f"{where}, reset")
    assert ends >= 4 and resets >= 2


@pytest.mark.parametrize("fast", [False, True], ids=["libm", "simd"])
def test_step_one_equals_step_kernel_beyond_the_small_angle(fast):
    # The block kernel integrates with small-angle polynomials for the heading increments and
    # redoes a lane whose increment exceeds SMALL_ANGLE with libm; the one-lane kernel takes the
    # libm-beyond-SMALL_ANGLE path at once. Both must give the same bits when the follower
    # spins (|r| h / 2 beyond SMALL_ANGLE) and when it does not, and when the target turns fast.
    a, b = _pair("S4", {"version": "v1", "tier": "Hard"}, fast)
    kernel, buf = b.step_one_call()
    a.reset(IDX0, [np.random.default_rng(4)])
    b.reset(IDX0, [np.random.default_rng(4)])
    hh = a.config.dt / a.config.physics_substeps / 2
    spin = 1.5 * dyn.SMALL_ANGLE / hh  # [rad/s]: the first stage's heading increment r h / 2 is beyond it
    for sim in (a, b):
        sim.params[0, dyn.P_TAR] = spin  # the target's yaw-rate tone and its bound: it turns as fast
        sim.params[0, dyn.P_RMAX] = 2.0 * spin
    rng = np.random.default_rng(5)
    turns = []
    for t in range(40):
        if t % 10 == 0:  # now and then spin the follower up (the state arrays are the sims' own)
            a.state[0, 5] = b.state[0, 5] = spin * (1.0 if t % 20 else -1.0)
        psi0 = a.state[0, 2]
        act = rng.uniform(-1.0, 1.0, 3)
        assert a.step(act) == -1
        assert kernel(buf, act)[0] == -1
        _assert_same(a, b, f"step {t}")
        turns.append(abs(a.state[0, 2] - psi0))
    # the spun-up steps turn by more than a substep's worth of SMALL_ANGLE increments: the
    # block kernel took its redo path there
    assert min(turns[::10]) > 2 * dyn.SMALL_ANGLE


def test_step_one_rejects_non_finite_actions_unchanged():
    a, b = _pair("S4", {"version": "v1", "tier": "Extreme"}, False)
    a.reset(IDX0, [np.random.default_rng(0)])
    b.reset(IDX0, [np.random.default_rng(0)])
    kernel, buf = b.step_one_call()
    for _ in range(5):
        a.step(np.full(3, 0.3))
        kernel(buf, np.full(3, 0.3))
    before = buf.copy()
    for bad_action in ([np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0, -np.inf]):
        assert kernel(buf, np.array(bad_action))[0] == 0
        assert a.step(np.array(bad_action)) == 0
    assert np.array_equal(buf.view(np.uint8), before.view(np.uint8))
    _assert_same(a, b, "after bad actions")


def _rollout(env: gym.Env, seed: int, actions: np.ndarray) -> list[tuple]:
    out = [env.reset(seed=seed)]
    done = False
    for a in actions:
        if done:
            out.append(env.reset())
            done = False
        else:
            res = env.step(a)
            out.append(res)
            done = res[2] or res[3]
    return out


@pytest.mark.parametrize("env_id, kwargs", [
    ("AUVFollow-S4-v0", {"episode_s": 6.0, "steady_start_s": 2.0, "max_distance_m": 2.5}),
    ("AUVFollow-Hard-v1", {"episode_s": 6.0, "steady_start_s": 2.0, "max_distance_m": 3.0}),
    ("AUVFollow-Extreme-v1", {"episode_s": 6.0, "steady_start_s": 2.0, "sincos": "libm"}),
])
def test_single_env_equals_the_vector_env(env_id, kwargs):
    n, steps = 3, 400
    actions = np.random.default_rng(3).uniform(-1.2, 1.2, (steps, n, 3)).astype(np.float32)
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kwargs)
    vec = [venv.reset(seed=5)] + [venv.step(a) for a in actions]
    ends = 0
    for i in range(n):
        single = _rollout(gym.make(env_id, **kwargs), 5 + i, actions[:, i])
        assert len(single) == len(vec)
        for t, (v, s) in enumerate(zip(vec, single, strict=True)):
            if len(s) == 2:  # a reset: (obs, info); the vector env autoresets on this step
                np.testing.assert_array_equal(v[0][i], s[0], err_msg=f"env {i}, step {t}")
                continue
            obs, rew, term, trunc, info = s
            np.testing.assert_array_equal(v[0][i], obs, err_msg=f"env {i}, step {t}")
            assert v[1][i] == rew and v[2][i] == term and v[3][i] == trunc, f"env {i}, step {t}"
            assert type(rew) is float and type(term) is bool and type(trunc) is bool
            vinfo = v[4]
            for key in ("tracking_error", "time", "true_target", "true_reference", "follower_pose"):
                np.testing.assert_array_equal(vinfo[key][i], info[key], err_msg=f"env {i}, step {t}, {key}")
            assert type(info["tracking_error"]) is float and type(info["time"]) is float
            if "episode_metrics" in info:
                ends += 1
                for key, val in info["episode_metrics"].items():
                    np.testing.assert_array_equal(vinfo["episode_metrics"][key][i], val)
                if "link_stats" in info:
                    for key, val in info["link_stats"].items():
                        assert vinfo["link_stats"][key][i] == val
    assert ends >= 3


def test_single_env_is_packed():
    env = gym.make("AUVFollow-S4-v0").unwrapped
    assert env._sim.buf is not None and np.shares_memory(env._sim.state, env._sim.buf)
    assert auv_follow_env.kernel_one.step_one is step_one


def test_the_cache_key_follows_dynamics_py():
    # numba keys a cached kernel on its own file and its closure variables: step_one compiles
    # dynamics' code into itself, so dynamics.py's hash must be among them (else an edit there
    # would leave a stale step_one in the on-disk cache)
    import hashlib
    from pathlib import Path

    digest = hashlib.sha256(Path(dyn.__file__).read_bytes()).hexdigest()
    assert digest in [c.cell_contents for c in step_one.py_func.__closure__]


@pytest.mark.parametrize("env_id", ["AUVFollow-S4-v0", "AUVFollow-Hard-v1"])
def test_a_reset_gives_each_env_the_same_episode_whatever_the_envs_reset_with_it(env_id):
    """The reset kernel warms a block of envs up at once (lanes of a SIMD block, padded to whole
    vectors for small groups): every env's arrays after the reset equal those of the same env
    reset alone (a block of one lane), bit for bit, for groups of 2 to 37 envs."""
    venv = gym.make_vec(env_id, num_envs=40, vectorization_mode="vector_entry_point", parallel=False)
    venv.reset(seed=3)  # draws every env's parameter row
    sim = venv.unwrapped._sim
    arrays = ("state", "k", "proc", "queue", "rs", "obs", "truth")
    seeds = np.arange(1000, 1040, dtype=np.int64)
    dirs = np.linspace(-3.0, 3.0, 40)

    def reset(idx):
        a = {name: getattr(sim, name).copy() for name in (*arrays, "params")}
        dyn.reset_kernel(a["state"], a["k"], a["proc"], a["queue"], a["rs"], a["params"], sim.cfg, idx, seeds[idx],
                         dirs[idx], a["obs"], a["truth"])
        return a

    alone = [reset(np.array([i])) for i in range(40)]
    for group in ([0, 1], [2, 3, 4], [5, 6, 7, 8, 9], [10, 39, 11, 12, 13, 14, 15], list(range(1, 38))):
        together = reset(np.array(group))
        for i in group:
            for name in arrays:
                np.testing.assert_array_equal(together[name][i], alone[i][name][i], err_msg=f"{name} of env {i}")
