"""The compiled passes of HierarchicalController give what the numpy composition of
predict_target / reference_point / outer_loop / inner_loop gives (``_fused = False``), on both
layouts, every variant, resets, held envs and odd values, serial and (from THREADED_MIN_ENVS
envs) on numba's threads; the reference cache is used only for the same bits and never goes
stale.

What is compared exactly and what within a bound. The two paths take their sin, cos and
arctan2 from different libraries: the compiled one from LLVM's libm calls, the numpy one from
numpy's own SIMD loops, which numpy picks at run time by CPU (on AVX-512 hosts its float64
loops differ from libm in the last bits; numpy documents them as within 4 ulp). So the two
agree bit for bit on some hosts and not on others, and the test compares them within
``FORCE_TOL`` (see its comment for the bound); NaN and infinity must sit in the same places.
``test_bound_covers_a_libm_that_differs_by_4_ulp`` emulates such a host here, whatever the CPU,
by moving every numpy sin/cos/arctan2 result by up to 4 ulp. The reference cache and the
action clip compare one implementation with itself in one process: exactly.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from auv_follow_env.layout import OBS_DIM, OBS_DIM_V1, OBS_INDEX, OBS_INDEX_V1
from auv_follow_env.params import make_task_spec
from controllers import make_controller
from controllers.base import ScriptedPolicy
from controllers.hierarchical import THREADED_MIN_ENVS

S4 = make_task_spec("S4")


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal bits, NaN equal to NaN (IEEE leaves the sign of a NaN result open)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    na, nb = np.isnan(a), np.isnan(b)
    ints = np.int32 if a.dtype == np.float32 else np.int64
    return bool(np.array_equal(na, nb) and np.array_equal(a[~na].view(ints), b[~nb].view(ints)))


# The bound, worked out from the law: an input angle that is off by 4 ulp (at most 4 * 2.2e-16 *
# pi = 2.8e-15 rad) rotates a vector of at most a few metres by under 1e-14 m; the law's
# sensitivity to positions is at most its gains times the mass (about 1e3 N per m here), so a
# force moves by ~1e-11 N (the emulation below measures 1.3e-11 N at forces up to 9e3 N). The
# bound, 1e-9 N plus 1e-12 of the force, leaves a margin of about 100 and is still six orders of
# magnitude below any wrong term of the law (the smallest gain times a centimetre is ~1e-2 N).
# The actions are float32 of the clipped force ratio in [-1, 1]: a last-bit force difference can
# round to the neighbouring float32, one ulp at 1 is 2**-23.
FORCE_TOL = dict(rtol=1e-12, atol=1e-9)
ACTION_TOL = dict(rtol=0.0, atol=2.0**-23)


def _close(a: np.ndarray, b: np.ndarray, *, rtol: float, atol: float) -> bool:
    """Same shape and dtype, NaN and +-inf in the same places, finite values within the bound."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if not (np.array_equal(np.isnan(a), np.isnan(b)) and np.array_equal(np.isposinf(a), np.isposinf(b))
            and np.array_equal(np.isneginf(a), np.isneginf(b))):
        return False
    fin = np.isfinite(a)
    x, y = a[fin].astype(np.float64), b[fin].astype(np.float64)
    return bool(np.all(np.abs(x - y) <= atol + rtol * np.maximum(np.abs(x), np.abs(y))))


def _batch(rng: np.random.Generator, n: int, width: int, odd: bool) -> np.ndarray:
    o = rng.uniform(-2.0, 2.0, (n, width))
    dpsi = rng.uniform(-4.0, 4.0, n)
    o[:, OBS_INDEX["target_cos_dpsi"]], o[:, OBS_INDEX["target_sin_dpsi"]] = np.cos(dpsi), np.sin(dpsi)
    o[:, OBS_INDEX["target_r"]] *= 0.1
    if width == OBS_DIM_V1:
        o[:, OBS_INDEX_V1["packet_age"]] = rng.uniform(0.0, 6.0, n)
        o[:, OBS_INDEX_V1["has_packet"]] = (rng.uniform(size=n) > 0.3).astype(float)
    if odd:  # signed zeros (arctan2(+-0, -1) = +-pi), a wrapped heading, huge, inf and NaN entries
        o[0] = -0.0
        o[1, OBS_INDEX["target_sin_dpsi"]], o[1, OBS_INDEX["target_cos_dpsi"]] = -0.0, -1.0
        o[2, OBS_INDEX["target_sin_dpsi"]], o[2, OBS_INDEX["target_cos_dpsi"]] = 0.0, -1.0
        o[3, OBS_INDEX["target_r"]] = 1e300
        o[4, OBS_INDEX["u"]] = np.inf
        o[5, OBS_INDEX["target_dx"]] = np.nan
        o[6, OBS_INDEX["current_v"]] = -np.inf
        if width == OBS_DIM_V1:
            o[7, OBS_INDEX_V1["has_packet"]] = np.nan
            o[8, OBS_INDEX_V1["has_packet"]] = 0.5
    return o


class _NoHold:
    """Off: the kernels themselves must agree on NaN and inf (the recovery rule, which keeps them
    from reaching the kernels through predict, is tested in test_nonfinite_obs.py)."""

    def __call__(self, obs, start=None, commit=True):
        return obs

    def reset(self):
        pass


def _compare_paths(name: str, width: int) -> None:
    rng = np.random.default_rng(11)
    fused, numpy_ = make_controller(name, S4), make_controller(name, S4)
    fused.hold = numpy_.hold = _NoHold()
    numpy_._fused = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for k in range(12):
            # a new batch size restarts every env; from THREADED_MIN_ENVS envs the passes run on threads
            n = (40 if k < 5 else THREADED_MIN_ENVS + 44) if k < 8 else 17
            o = _batch(rng, n, width, odd=k % 2 == 0)
            obs = o.astype(np.float32) if k % 3 == 0 else o
            start = rng.uniform(size=n) < 0.25 if k % 4 == 1 else None
            if k % 2:  # the evaluation order: reference first, then predict on the same batch
                assert _close(fused.reference(obs), numpy_.reference(obs), **FORCE_TOL)
            a, _ = fused.predict(obs, episode_start=start)
            b, _ = numpy_.predict(obs, episode_start=start)
            assert _close(a, b, **ACTION_TOL), f"actions, call {k}"
            assert _close(fused.last_forces, numpy_.last_forces, **FORCE_TOL), f"forces, call {k}"
            assert _close(fused.reference(obs), numpy_.reference(obs), **FORCE_TOL), f"reference, call {k}"
            assert _close(fused._diff.d, numpy_._diff.d, **FORCE_TOL)
            assert _close(fused._diff.prev, numpy_._diff.prev, **FORCE_TOL)
            a, _ = fused.predict(obs[3])  # one observation: a batch of one, restarted
            b, _ = numpy_.predict(obs[3])
            assert _close(a, b, **ACTION_TOL)
            fused.reset()
            numpy_.reset()


@pytest.mark.parametrize("width", [OBS_DIM, OBS_DIM_V1])
@pytest.mark.parametrize("name", ["PROPOSED", "PRED_ONLY", "ROBUST_ONLY"])
def test_fused_law_equals_the_numpy_composition(name, width):
    _compare_paths(name, width)


class _Libm4Ulp:
    """numpy as seen by the controllers, with sin, cos and arctan2 results moved by a random
    -4..4 ulp, except exact results (0, +-1, +-pi/2, +-pi, non-finite), which every libm keeps."""

    def __init__(self, rng: np.random.Generator):
        self._rng = rng
        for fn in ("sin", "cos", "arctan2"):
            setattr(self, fn, self._moved(getattr(np, fn)))

    def __getattr__(self, attr):
        return getattr(np, attr)

    def _moved(self, f):
        def g(*args, **kwargs):
            y = np.array(f(*args, **kwargs), dtype=np.float64)
            steps = self._rng.integers(-4, 5, size=y.shape)
            steps[np.isin(np.abs(y), [0.0, 1.0, np.pi / 2, np.pi]) | ~np.isfinite(y)] = 0
            for _ in range(4):
                up, down = steps > 0, steps < 0
                y[up], y[down] = np.nextafter(y[up], np.inf), np.nextafter(y[down], -np.inf)
                steps[up] -= 1
                steps[down] += 1
            return y
        return g


@pytest.mark.parametrize("width", [OBS_DIM, OBS_DIM_V1])
def test_bound_covers_a_libm_that_differs_by_4_ulp(width, monkeypatch):
    import controllers.base
    import controllers.hierarchical

    fake = _Libm4Ulp(np.random.default_rng(0))
    monkeypatch.setattr(controllers.hierarchical, "np", fake)
    monkeypatch.setattr(controllers.base, "np", fake)
    for name in ("PROPOSED", "ROBUST_ONLY"):
        _compare_paths(name, width)


def test_reference_cache_needs_the_same_bits_and_settings():
    rng = np.random.default_rng(2)
    c = make_controller("PROPOSED", S4)
    o = _batch(rng, 8, OBS_DIM, odd=False)
    ref0 = c.reference(o)
    assert c._cached_reference(o) is not None
    o2 = o.copy()
    o2[3, OBS_INDEX["target_dx"]] = np.nextafter(o2[3, OBS_INDEX["target_dx"]], 9.0)  # one ulp
    assert c._cached_reference(o2) is None
    o2 = o.copy()
    o2[0, OBS_INDEX["target_dy"]] = 0.0
    o3 = o2.copy()
    o3[0, OBS_INDEX["target_dy"]] = -0.0  # equal as numbers, not as bits
    c.reference(o2)
    assert c._cached_reference(o3) is None
    # the caller's float64 array is copied: changing it in place cannot make the cache stale
    c.reference(o)
    o[:, OBS_INDEX["target_dx"]] += 1.0
    assert c._cached_reference(o) is None
    c.reference(o)
    c.prediction = False  # another setting: recomputed
    assert c._cached_reference(o) is None
    # the returned reference is the caller's: changing it leaves the cache intact
    c.prediction = True
    r = c.reference(o)
    r[:] = 7.0
    fresh = make_controller("PROPOSED", S4).reference(o)
    assert not np.array_equal(fresh, ref0)
    np.testing.assert_array_equal(c._cached_reference(o)[0], fresh)


def test_forces_reuse_the_reference_of_the_same_observation(monkeypatch):
    rng = np.random.default_rng(4)
    c = make_controller("PROPOSED", S4)
    o = _batch(rng, 16, OBS_DIM, odd=False).astype(np.float32)
    c.predict(o)
    calls = []
    real = c._fused_reference
    monkeypatch.setattr(c, "_fused_reference", lambda a: calls.append(1) or real(a))
    c.reference(o)
    assert len(calls) == 1
    c.predict(o)  # the same observation: no second computation
    assert len(calls) == 1
    c.predict(o + np.float32(0.01))
    assert len(calls) == 2


def test_actions_pass_equals_the_numpy_clip():
    rng = np.random.default_rng(7)
    p = ScriptedPolicy(S4)
    F = rng.normal(scale=300.0, size=(64, 3))
    F[:5] = [[np.inf, -np.inf, -0.0], [0.0, 1e-320, -1e-320], [np.nan, 1.0, -1.0], [1e308, -1e308, 5.0],
             [p._limits[0], -p._limits[1], p._limits[2] * (1 + 1e-16)]]
    p.forces = lambda obs, mask: F  # type: ignore[method-assign]
    a, _ = p.predict(np.zeros((64, OBS_DIM)))
    assert _same(a, np.clip(F / p._limits, -1.0, 1.0).astype(np.float32))


# --- the estimator controllers: the compiled law on the estimator's output ------------------
def _leader_obs_stream(n: int, steps: int, seed: int):
    """Observations of n Leader-Hard episodes driven by PROPOSED_IMM_DOB (float64, as predict sees
    them), with a few episode restarts."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401

    venv = gym.make_vec("AUVFollow-Leader-Hard-v1", num_envs=n, vectorization_mode="vector_entry_point",
                        episode_s=10.0, steady_start_s=5.0)
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    driver = make_controller("PROPOSED_IMM_DOB", spec)
    obs, _ = venv.reset(seed=list(range(seed, seed + n)))
    start = np.ones(n, dtype=bool)
    out = []
    for _ in range(steps):
        o = np.asarray(obs, dtype=np.float64)
        out.append((o, start.copy()))
        a, _ = driver.predict(o, episode_start=start)
        obs, _, term, trunc, _ = venv.step(a)
        start = term | trunc
    venv.close()
    return spec, out


@pytest.mark.parametrize(("name", "n"), [("PROPOSED_KF_DOB", 6), ("PROPOSED_KF_DOB", THREADED_MIN_ENVS + 12),
                                         ("PROPOSED_IMM_DOB", 6), ("PROPOSED_IMM_DOB", THREADED_MIN_ENVS + 12),
                                         ("PROPOSED_PF_DOB", 6)])  # (the passes do not depend on the filter)
def test_estimator_law_equals_the_numpy_composition(name, n):
    """reference() and predict() of the estimator controllers: the compiled passes on the
    estimate give the numpy composition's reference, forces, actions, derivative state and
    disturbance estimate within the bound, along real episodes (fixes, held envs before the
    first packet, restarts; serial and threaded batches). A restart mask is forced on a few envs
    mid-run."""
    spec, stream = _leader_obs_stream(n, 60 if name != "PROPOSED_PF_DOB" else 25, seed=40)
    fused, numpy_ = make_controller(name, spec), make_controller(name, spec)
    numpy_._fused = False
    assert fused._uses_fused_estimate(stream[0][0]) and not numpy_._uses_fused_estimate(stream[0][0])
    for k, (o, start) in enumerate(stream):
        if k == 17:
            start = start.copy()
            start[::3] = True
        assert _close(fused.reference(o), numpy_.reference(o), **FORCE_TOL), f"reference, step {k}"
        a, _ = fused.predict(o, episode_start=start)
        b, _ = numpy_.predict(o, episode_start=start)
        assert _close(a, b, **ACTION_TOL), f"actions, step {k}"
        assert _close(fused.last_forces, numpy_.last_forces, **FORCE_TOL), f"forces, step {k}"
        assert _close(fused._diff.d, numpy_._diff.d, **FORCE_TOL)
        dob_f, dob_n = fused.disturbance_observer, numpy_.disturbance_observer
        assert _close(dob_f.d_hat, dob_n.d_hat, **FORCE_TOL) and _close(dob_f._f, dob_n._f, **FORCE_TOL)
    # the hold before the first packet is exercised: some envs had no fix at the first steps
    assert (stream[0][0][:, OBS_INDEX_V1["has_packet"]] < 0.5).any()


def test_observer_correct_equals_update_then_applied():
    """DisturbanceObserver.correct (compiled) = F - update(nu, current, mask), then applied(F):
    the same arithmetic, so the same bits in one process; first call, restarts, a new batch size,
    saturation and NaN included."""
    from controllers.disturbance import DisturbanceObserver

    rng = np.random.default_rng(5)
    lim = (400.0, 300.0, 150.0)
    a_obs = DisturbanceObserver(S4.nominal, 0.05, lim, 0.5)
    b_obs = DisturbanceObserver(S4.nominal, 0.05, lim, 0.5)
    for k in range(30):
        n = 7 if k < 20 else THREADED_MIN_ENVS + 3
        o = rng.normal(size=(n, OBS_DIM_V1)) * (50.0 if k == 9 else 1.0)
        if k == 11:
            o[2, OBS_INDEX["u"]] = np.nan
        mask = rng.uniform(size=n) < 0.2
        F = rng.normal(scale=500.0, size=(n, 3))
        Fa = F.copy()
        a_obs.correct(o, mask, Fa)
        nu = o[:, [OBS_INDEX["u"], OBS_INDEX["v"], OBS_INDEX["r"]]]
        cur = o[:, [OBS_INDEX["current_u"], OBS_INDEX["current_v"]]]
        Fb = F - b_obs.update(nu, cur, mask)
        b_obs.applied(Fb)
        assert _same(Fa, Fb), f"forces, call {k}"
        assert _same(a_obs.d_hat, b_obs.d_hat) and _same(a_obs._f, b_obs._f), f"state, call {k}"
    with_lag = DisturbanceObserver(S4.nominal, 0.05, lim, 0.5, thruster_tc_s=0.2)
    assert not with_lag.fusable
    with pytest.raises(ValueError, match="thruster model"):
        with_lag.correct(o, mask, F.copy())
