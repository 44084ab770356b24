"""The SIMD sin/cos polynomial (``sincos="simd"``, the default since 0.2.0; formerly the opt-in
``fast_math``) against glibc's (``sincos="libm"``), and what it does (and does not do) to results.

The reference values are numpy's extended-precision (x87, 64-bit mantissa) sin/cos, which
are independent of both the polynomial and glibc's double-precision sin/cos."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from numba import njit

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env import dynamics as dyn
from auv_follow_env.env import AUVFollowEnv
from auv_follow_env.vector_env import AUVFollowVectorEnv
from controllers import make_controller

HAS_LONGDOUBLE = np.finfo(np.longdouble).nmant >= 63


@njit
def _fast_all(x, s, c):
    for i in range(x.shape[0]):
        s[i], c[i] = dyn.fast_sincos(x[i])


@njit
def _rows(x, fast):
    """dyn._sincos_rows over one block-sized row of arguments (row 0 -> rows 1 and 2)."""
    wk = np.zeros(3 * dyn.BLOCK)
    m = x.shape[0]
    for b in range(m):
        wk[b] = x[b]
    dyn._sincos_rows(wk, 0, 1, 2, m, fast)
    return wk[dyn.BLOCK:dyn.BLOCK + m].copy(), wk[2 * dyn.BLOCK:2 * dyn.BLOCK + m].copy()


def _ulps(got: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """|got - exact| in units of the last place of the double nearest to the exact value."""
    nearest = exact.astype(np.float64)
    return (np.abs(got.astype(np.longdouble) - exact) / np.spacing(np.abs(nearest)).astype(np.longdouble)).astype(
        np.float64)


@pytest.mark.skipif(not HAS_LONGDOUBLE, reason="needs an extended-precision long double reference")
@pytest.mark.parametrize("lo,hi", [(-np.pi / 4, np.pi / 4), (-4.0, 4.0), (-70.0, 70.0), (-1e5, 1e5)])
def test_fast_sincos_is_within_one_ulp(lo, hi):
    x = np.random.default_rng(7).uniform(lo, hi, 200_000)
    s, c = np.empty_like(x), np.empty_like(x)
    _fast_all(x, s, c)
    xl = x.astype(np.longdouble)
    assert _ulps(s, np.sin(xl)).max() <= 1.0
    assert _ulps(c, np.cos(xl)).max() <= 1.0


def test_fast_sincos_exact_points_and_quadrants():
    s, c = np.empty(1), np.empty(1)
    _fast_all(np.zeros(1), s, c)
    assert (s[0], c[0]) == (0.0, 1.0)
    # the quadrant logic: sin/cos of k pi/2 + 0.3 against the closed forms
    base_s, base_c = np.sin(0.3), np.cos(0.3)
    expected = {0: (base_s, base_c), 1: (base_c, -base_s), 2: (-base_s, -base_c), 3: (-base_c, base_s)}
    for k in range(-8, 9):
        x = np.array([k * np.pi / 2 + 0.3])
        _fast_all(x, s, c)
        es, ec = expected[k % 4]
        assert s[0] == pytest.approx(es, abs=1e-14) and c[0] == pytest.approx(ec, abs=1e-14), k


@njit
def _log_all(x, out):
    for i in range(x.shape[0]):
        out[i] = dyn.fast_log(x[i])


@pytest.mark.skipif(not HAS_LONGDOUBLE, reason="needs an extended-precision long double reference")
def test_fast_log_is_within_one_ulp():
    """The Box-Muller radius' logarithm (uniforms in (0, 1], and any positive normal double)."""
    rng = np.random.default_rng(11)
    x = np.concatenate([1.0 - rng.random(200_000),  # the generator's u1
                        1.0 - rng.uniform(0, 1e-6, 20_000),  # near 1, where log is near 0
                        np.exp(rng.uniform(-700.0, 700.0, 50_000)),
                        [2.0 ** -53, 0.5, 2.0, np.sqrt(2.0), np.sqrt(0.5), np.nextafter(1.0, 0.0)]])
    out = np.empty_like(x)
    _log_all(x, out)
    assert _ulps(out, np.log(x.astype(np.longdouble))).max() <= 1.0
    one = np.empty(1)
    _log_all(np.ones(1), one)
    assert one[0] == 0.0  # log 1 = 0 exactly (a uniform of 0 gives the radius 0)
    _log_all(np.array([0.25]), one)
    assert one[0] == -2.0 * np.log(2.0)  # exact in two roundings: -2 ln 2 rounds once


def test_sincos_rows_fall_back_to_libm_for_huge_arguments():
    x = np.array([0.5, 3.0e7, -2.0e6, 1.0])  # two lanes beyond FAST_TRIG_MAX
    s, c = _rows(x, True)
    big = np.abs(x) > dyn.FAST_TRIG_MAX
    assert big.sum() == 2
    np.testing.assert_array_equal(s[big], np.array([np.sin(v) for v in x[big]]))
    np.testing.assert_array_equal(c[big], np.array([np.cos(v) for v in x[big]]))
    s0, c0 = _rows(x, False)  # libm everywhere: the default path
    np.testing.assert_array_equal(s0, [np.sin(v) for v in x])
    np.testing.assert_array_equal(c0, [np.cos(v) for v in x])


def _proposed_run(env_id: str, seeds: list[int], fast: bool):
    venv = gym.make_vec(env_id, num_envs=len(seeds), vectorization_mode="vector_entry_point", parallel=False,
                        sincos="simd" if fast else "libm")
    spec = venv.unwrapped.task_spec
    obs, _ = venv.reset(seed=seeds)
    pol = make_controller("PROPOSED", spec)
    first = np.ones(len(seeds), dtype=bool)
    poses, ends = [], []
    for _ in range(spec.n_steps):
        a, _ = pol.predict(obs, episode_start=first)
        first[:] = False
        obs, _, term, trunc, info = venv.step(a)
        poses.append(info["follower_pose"].copy())
        ends.append(term | trunc)
    venv.close()
    return np.array(poses), np.array(ends)


@pytest.mark.parametrize("env_id,seeds", [("AUVFollow-S4-v0", list(range(6))),
                                          ("AUVFollow-Hard-v1", list(range(3_000_000, 3_000_006)))])
def test_simd_trajectories_stay_within_1e_12_of_libm(env_id, seeds):
    """Full 60 s PROPOSED episodes: the follower's pose differs by rounding only (the issue's
    bound is 1e-12; the float32 observations absorb last-bit differences of the state)."""
    exact, ends0 = _proposed_run(env_id, seeds, False)
    fast, ends1 = _proposed_run(env_id, seeds, True)
    np.testing.assert_array_equal(ends0, ends1)
    assert np.abs(fast - exact).max() < 1e-12
    assert not np.array_equal(fast, exact)  # it is a different computation, not libm again


def test_simd_parallel_equals_serial_bit_for_bit():
    n = 512
    acts = np.random.default_rng(3).uniform(-1, 1, (30, n, 3)).astype(np.float32)
    out = []
    for par in (False, True):
        venv = AUVFollowVectorEnv(num_envs=n, parallel=par)
        obs, _ = venv.reset(seed=11)
        for a in acts:
            obs, *_ = venv.step(a)
        out.append((obs.copy(), venv._sim.state.copy()))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])


@pytest.mark.parametrize("sincos", ["simd", "libm"])
def test_single_env_equals_the_vector_env(sincos):
    env = AUVFollowEnv(sincos=sincos)
    venv = AUVFollowVectorEnv(num_envs=1, sincos=sincos)
    o1, _ = env.reset(seed=4)
    o2, _ = venv.reset(seed=4)
    acts = np.random.default_rng(0).uniform(-1, 1, (50, 3)).astype(np.float32)
    for a in acts:
        o1, *_ = env.step(a)
        o2, *_ = venv.step(a[None])
    np.testing.assert_array_equal(o1, o2[0])
    np.testing.assert_array_equal(env.unwrapped._sim.state, venv._sim.state)
    assert env.sincos == venv.sincos == sincos


def _poses(**kw) -> np.ndarray:
    env = gym.make("AUVFollow-S4-v0", **kw)
    env.reset(seed=2)
    acts = np.random.default_rng(1).uniform(-1, 1, (600, 3)).astype(np.float32)  # (terminates at 888)
    out = np.array([np.r_[info["follower_pose"], info["true_target"]] for info in (env.step(a)[4] for a in acts)])
    env.close()
    return out


def test_default_is_simd_and_libm_is_the_named_opt_in():
    assert AUVFollowVectorEnv(num_envs=2).sincos == "simd"
    env = gym.make("AUVFollow-Hard-v1")
    assert env.unwrapped.sincos == "simd" and env.unwrapped.fast_math is True
    default, simd, libm = _poses(), _poses(sincos="simd"), _poses(sincos="libm")
    np.testing.assert_array_equal(default, simd)
    assert not np.array_equal(default, libm)
    assert np.abs(default - libm).max() < 1e-12


def test_former_keyword_fast_math_keeps_its_meaning():
    """fast_math=True is sincos="simd" and fast_math=False is sincos="libm", bit for bit."""
    np.testing.assert_array_equal(_poses(fast_math=True), _poses(sincos="simd"))
    np.testing.assert_array_equal(_poses(fast_math=False), _poses(sincos="libm"))
    assert gym.make("AUVFollow-S4-v0", fast_math=False).unwrapped.sincos == "libm"
    assert AUVFollowVectorEnv(num_envs=2, fast_math=True, sincos="simd").sincos == "simd"  # consistent: fine


@pytest.mark.parametrize("bad", [1, "yes", 0.0])
def test_fast_math_must_be_a_bool(bad):
    with pytest.raises(ValueError, match="fast_math"):
        AUVFollowVectorEnv(num_envs=2, fast_math=bad)
    with pytest.raises(ValueError, match="fast_math"):
        gym.make("AUVFollow-S4-v0", fast_math=bad)


@pytest.mark.parametrize("bad", ["SIMD", "fast", 1, True])
def test_sincos_must_be_simd_or_libm(bad):
    for make in (lambda: AUVFollowVectorEnv(num_envs=2, sincos=bad), lambda: gym.make("AUVFollow-S4-v0", sincos=bad)):
        with pytest.raises(ValueError, match=r"sincos=.*'simd'.*'libm'"):
            make()


def test_fast_math_contradicting_sincos_is_refused():
    with pytest.raises(ValueError, match=r"fast_math=True contradicts sincos='libm'"):
        gym.make("AUVFollow-S4-v0", fast_math=True, sincos="libm")
    with pytest.raises(ValueError, match=r"fast_math=False contradicts sincos='simd'"):
        AUVFollowVectorEnv(num_envs=2, fast_math=False, sincos="simd")
