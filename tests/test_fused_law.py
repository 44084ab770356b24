"""The compiled passes of HierarchicalController give, bit for bit, what the numpy composition
of predict_target / reference_point / outer_loop / inner_loop gives (``_fused = False``), on
both layouts, every variant, resets, held envs and odd values, serial and (from
THREADED_MIN_ENVS envs) on numba's threads; the reference cache is used only for the same bits
and never goes stale."""

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


@pytest.mark.parametrize("width", [OBS_DIM, OBS_DIM_V1])
@pytest.mark.parametrize("name", ["PROPOSED", "PRED_ONLY", "ROBUST_ONLY"])
def test_fused_law_is_bit_identical_to_the_numpy_composition(name, width):
    rng = np.random.default_rng(11)
    fused, numpy_ = make_controller(name, S4), make_controller(name, S4)
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
                assert _same(fused.reference(obs), numpy_.reference(obs))
            a, _ = fused.predict(obs, episode_start=start)
            b, _ = numpy_.predict(obs, episode_start=start)
            assert _same(a, b), f"actions, call {k}"
            assert _same(fused.last_forces, numpy_.last_forces), f"forces, call {k}"
            assert _same(fused.reference(obs), numpy_.reference(obs)), f"reference, call {k}"
            assert _same(fused._diff.d, numpy_._diff.d) and _same(fused._diff.prev, numpy_._diff.prev)
            a, _ = fused.predict(obs[3])  # one observation: a batch of one, restarted
            b, _ = numpy_.predict(obs[3])
            assert _same(a, b)
            fused.reset()
            numpy_.reset()


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
