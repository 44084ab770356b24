"""tracking_metrics / window_metrics (eqs. (64)-(65)) on hand-computed arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from auv_follow_env.metrics import METRIC_KEYS, tracking_metrics, window_metrics


def test_window_metrics_by_hand():
    mean, rmse, mx = window_metrics(np.array([3.0, 4.0]))
    assert mean == 3.5
    assert rmse == pytest.approx(math.sqrt(12.5), rel=1e-15)
    assert mx == 4.0
    # one sample: all three equal it
    assert window_metrics(np.array([0.25])) == (0.25, 0.25, 0.25)


def test_window_metrics_empty_is_nan():
    assert all(math.isnan(v) for v in window_metrics(np.array([])))


def test_tracking_metrics_keys_and_full_window():
    m = tracking_metrics(np.array([3.0, 4.0]), np.array([0.05, 0.10]), steady_start=10.0)
    assert tuple(m) == METRIC_KEYS
    assert m["full_mean"] == 3.5
    assert m["full_rmse"] == pytest.approx(math.sqrt(12.5))
    assert m["full_max"] == 4.0
    # no sample at or after 10 s: the steady window is empty -> NaN
    assert math.isnan(m["steady_mean"]) and math.isnan(m["steady_rmse"]) and math.isnan(m["steady_max"])


def test_steady_window_selected_by_time():
    e = np.array([10.0, 9.0, 1.0, 2.0, 2.0])
    t = np.array([8.0, 9.5, 10.0, 11.0, 12.0])
    m = tracking_metrics(e, t, steady_start=10.0)
    # full: mean 24/5, rmse sqrt((100 + 81 + 1 + 4 + 4) / 5) = sqrt(38), max 10
    assert m["full_mean"] == pytest.approx(4.8)
    assert m["full_rmse"] == pytest.approx(math.sqrt(38.0))
    assert m["full_max"] == 10.0
    # steady (t >= 10, the sample at exactly 10 s included): [1, 2, 2]
    assert m["steady_mean"] == pytest.approx(5.0 / 3.0)
    assert m["steady_rmse"] == pytest.approx(math.sqrt(3.0))
    assert m["steady_max"] == 2.0
    # another start moves the window
    m2 = tracking_metrics(e, t, steady_start=11.0)
    assert m2["steady_mean"] == 2.0 and m2["steady_rmse"] == 2.0 and m2["steady_max"] == 2.0


def test_steady_window_includes_a_float_rounded_boundary_sample():
    # 200 * 0.05 = 10.000000000000002 and 0.1 * 100 style rounding must not drop or add t = 10 s
    dt = 0.05
    t = dt * np.arange(1, 1201)
    e = np.where(t < 10.0 - 1e-6, 5.0, 1.0)
    m = tracking_metrics(e, t, steady_start=10.0)
    assert m["steady_mean"] == 1.0 and m["steady_max"] == 1.0
    # 1001 samples from t = 10 s to 60 s inclusive
    n_full = 1200
    n_steady = 1001
    assert m["full_mean"] == pytest.approx((5.0 * (n_full - n_steady) + n_steady) / n_full)


def test_rmse_inequality_holds():
    rng = np.random.default_rng(0)
    e = rng.random(500)
    t = np.linspace(0, 60, 500)
    m = tracking_metrics(e, t)
    for w in ("full", "steady"):
        assert m[f"{w}_rmse"] ** 2 <= m[f"{w}_max"] * m[f"{w}_mean"] + 1e-12
        assert m[f"{w}_mean"] <= m[f"{w}_rmse"] <= m[f"{w}_max"]


@pytest.mark.parametrize("e,t", [
    (np.zeros((2, 2)), np.zeros((2, 2))),
    (np.zeros(3), np.zeros(4)),
    (np.zeros(3), np.zeros((3, 1))),
    (np.float64(1.0), np.float64(1.0)),
])
def test_bad_shapes_raise(e, t):
    with pytest.raises(ValueError, match="1-D"):
        tracking_metrics(e, t)


def test_batch_tracking_metrics_by_hand_and_equal_to_the_single_episode_function():
    from auv_follow_env.metrics import batch_tracking_metrics

    e = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 4.0]])
    t = np.array([5.0, 10.0, 15.0])
    m = batch_tracking_metrics(e, t, steady_start=10.0)
    np.testing.assert_allclose(m["full_mean"], [2.0, 4.0 / 3.0])
    np.testing.assert_allclose(m["full_rmse"], [np.sqrt(14.0 / 3.0), np.sqrt(16.0 / 3.0)])
    np.testing.assert_array_equal(m["full_max"], [3.0, 4.0])
    np.testing.assert_allclose(m["steady_mean"], [2.5, 2.0])  # samples at t = 10 and 15
    np.testing.assert_allclose(m["steady_rmse"], [np.sqrt(6.5), np.sqrt(8.0)])
    assert np.isnan(batch_tracking_metrics(e, t, steady_start=99.0)["steady_mean"]).all()
    # bit for bit the per-episode function (the vector env's metrics must equal the single env's)
    rng = np.random.default_rng(0)
    for n in (1, 7, 1200, 9000):
        errs = rng.exponential(0.3, (9, n))
        times = 0.05 * np.arange(1, n + 1)
        batch = batch_tracking_metrics(errs, times, 10.0)
        for j in range(9):
            for key, value in tracking_metrics(errs[j], times, 10.0).items():
                assert value == batch[key][j] or (math.isnan(value) and math.isnan(batch[key][j])), (n, j, key)
    with pytest.raises(ValueError, match="errors must be"):
        batch_tracking_metrics(np.zeros(3), np.zeros(3))


def test_history_metrics_by_hand_and_bit_for_bit_the_numpy_function():
    """The compiled metrics of (envs x steps) histories: hand values, then every length
    0-300 and long ones against :func:`tracking_metrics` (numpy's pairwise sums) bit for bit."""
    from auv_follow_env.metrics import METRIC_KEYS, history_metrics

    hist = np.array([[1.0, 0.0, 9.0], [2.0, 0.0, 9.0], [3.0, 4.0, 9.0]]).T  # 3 envs x 3 steps
    t = np.array([5.0, 10.0, 15.0])
    out = history_metrics(hist, np.array([0, 1]), np.array([3, 3]), t, steady_start=10.0)
    assert out.shape == (6, 3)
    np.testing.assert_allclose(out[:, 0], [2.0, np.sqrt(14.0 / 3.0), 3.0, 2.5, np.sqrt(6.5), 3.0])
    np.testing.assert_allclose(out[:, 1], [4.0 / 3.0, np.sqrt(16.0 / 3.0), 4.0, 2.0, np.sqrt(8.0), 4.0])
    assert np.isnan(out[:, 2]).all()  # env 2 not listed
    short = history_metrics(hist, np.array([2]), np.array([1]), t, steady_start=10.0)  # only t = 5 s
    np.testing.assert_array_equal(short[:3, 2], [9.0, 9.0, 9.0])
    assert np.isnan(short[3:, 2]).all()  # no sample in the steady window
    assert np.isnan(history_metrics(hist, np.array([0]), np.array([0]), t)[:, 0]).all()
    rng = np.random.default_rng(1)
    lengths = np.r_[np.arange(0, 301), [1199, 1200, 2047, 4097, 9000]]
    S = int(lengths.max())
    hist = rng.exponential(0.3, (lengths.size, S)) * rng.uniform(0.01, 50.0, (lengths.size, 1))
    times = 0.05 * np.arange(1, S + 1)
    out = history_metrics(hist, np.arange(lengths.size), lengths, times, 10.0)
    assert out.shape == (6, lengths.size)
    for j, n in enumerate(lengths):
        ref = tracking_metrics(hist[j, :n].copy(), times[:n], 10.0) if n else dict.fromkeys(METRIC_KEYS, np.nan)
        for c, key in enumerate(METRIC_KEYS):
            v = out[c, j]
            assert v == ref[key] or (math.isnan(v) and math.isnan(ref[key])), (n, key, v, ref[key])
    with pytest.raises(ValueError, match="ids must be in"):
        history_metrics(hist, np.array([lengths.size]), np.array([1]), times)
    with pytest.raises(ValueError, match="lengths must be"):
        history_metrics(hist, np.array([0, 1]), np.array([1]), times)
    with pytest.raises(ValueError, match="float64"):
        history_metrics(hist.astype(np.float32), np.array([0]), np.array([1]), times)
