"""controllers.evaluation: evaluate / evaluate_controllers / evaluate_batched, the two
references (true and own), and the paper-level lag of controllers without prediction."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

import auv_follow_env
from auv_follow_env.metrics import METRIC_KEYS, tracking_metrics
from controllers import make_controller
from controllers.evaluation import (
    METRIC_COLUMNS,
    TRAJECTORY_COLUMNS,
    evaluate,
    evaluate_batched,
    evaluate_controllers,
)

SHORT = {"episode_s": 12.0, "max_episode_steps": 240}  # 240 steps of 0.05 s, steady window 10-12 s
S1_SHORT = auv_follow_env.make_task_spec("S1", episode_s=12.0)


class ZeroPolicy:
    """A policy without a ``reference`` method."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        obs = np.asarray(observation)
        return np.zeros(obs.shape[:-1] + (3,), dtype=np.float32), state


@pytest.fixture(scope="module")
def proposed_run():
    return evaluate(make_controller("PROPOSED", S1_SHORT), "AUVFollow-S1-v0", seeds=[0, 1],
                    env_kwargs=SHORT, trajectories=True, progress=False)


def test_metric_columns_are_true_then_own():
    assert METRIC_COLUMNS == tuple(f"true_{k}" for k in METRIC_KEYS) + tuple(f"own_{k}" for k in METRIC_KEYS)


def test_evaluate_one_row_per_seed(proposed_run):
    metrics, traj = proposed_run
    assert len(metrics) == 2
    assert list(metrics["seed"]) == [0, 1]
    for col in ("scenario", "disturbance", "policy", "seed", "steps", "terminated", "return", *METRIC_COLUMNS):
        assert col in metrics.columns
    assert (metrics["policy"] == "PROPOSED").all()
    assert (metrics["scenario"] == "S1").all()
    assert (metrics["steps"] == 240).all()
    assert not metrics["terminated"].any()
    assert np.isfinite(metrics[list(METRIC_COLUMNS)].to_numpy()).all()
    assert tuple(traj.columns) == TRAJECTORY_COLUMNS
    assert len(traj) == 480


def test_metrics_equal_tracking_metrics_of_the_trajectory(proposed_run):
    metrics, traj = proposed_run
    for _, row in metrics.iterrows():
        t = traj[traj["seed"] == row["seed"]]
        # times are t = dt, 2 dt, ..., T
        np.testing.assert_allclose(t["time"].to_numpy(), 0.05 * np.arange(1, 241), rtol=1e-12)
        m_true = tracking_metrics(t["err_true"].to_numpy(), t["time"].to_numpy(), 10.0)
        m_own = tracking_metrics(t["err_own"].to_numpy(), t["time"].to_numpy(), 10.0)
        for k in METRIC_KEYS:
            assert row[f"true_{k}"] == pytest.approx(m_true[k], rel=1e-12)
            assert row[f"own_{k}"] == pytest.approx(m_own[k], rel=1e-12)
        # steady window: 10 s .. 12 s is 41 samples; the mean is a plain mean of them
        steady = t["err_true"].to_numpy()[t["time"].to_numpy() >= 10.0 - 1e-9]
        assert steady.size == 41
        assert row["true_steady_mean"] == pytest.approx(steady.mean(), rel=1e-12)


def test_trajectory_errors_are_distances_to_the_references(proposed_run):
    _, traj = proposed_run
    d_true = np.hypot(traj["follower_x"] - traj["true_ref_x"], traj["follower_y"] - traj["true_ref_y"])
    d_own = np.hypot(traj["follower_x"] - traj["own_ref_x"], traj["follower_y"] - traj["own_ref_y"])
    np.testing.assert_allclose(traj["err_true"], d_true, atol=1e-9)
    np.testing.assert_allclose(traj["err_own"], d_own, atol=1e-9)
    # the true reference is p_t + R(psi_t) p_d of the present target
    c, s = np.cos(traj["target_psi"]), np.sin(traj["target_psi"])
    np.testing.assert_allclose(traj["true_ref_x"], traj["target_x"] + c * -0.65 - s * 0.12, atol=1e-9)
    np.testing.assert_allclose(traj["true_ref_y"], traj["target_y"] + s * -0.65 + c * 0.12, atol=1e-9)
    # forces within the limits
    assert (traj[["F_u", "F_v"]].abs() <= 150.0 + 1e-9).all().all()
    assert (traj["F_r"].abs() <= 30.0 + 1e-9).all()


def test_own_metrics_nan_without_reference_method():
    m = evaluate(ZeroPolicy(), "AUVFollow-S1-v0", seeds=[0], env_kwargs=SHORT, progress=False)
    assert len(m) == 1
    assert m["policy"].iloc[0] == "ZeroPolicy"
    for k in METRIC_KEYS:
        assert math.isnan(m[f"own_{k}"].iloc[0])
        assert math.isfinite(m[f"true_{k}"].iloc[0])


def test_identical_seeds_give_identical_rows():
    m = evaluate(make_controller("PID", S1_SHORT), "AUVFollow-S1-v0", seeds=[3, 3], env_kwargs=SHORT,
                 progress=False)
    a, b = m.iloc[0], m.iloc[1]
    for col in m.columns:
        assert a[col] == b[col], col
    # and another seed gives another episode
    m2 = evaluate(make_controller("PID", S1_SHORT), "AUVFollow-S1-v0", seeds=[4], env_kwargs=SHORT,
                  progress=False)
    assert m2["true_full_mean"].iloc[0] != a["true_full_mean"]


@pytest.mark.parametrize("seeds", [[-1], [0, -3], [1.5], ["0"], [], [True], [None]])
def test_bad_seeds_raise(seeds):
    with pytest.raises(ValueError):
        evaluate(ZeroPolicy(), "AUVFollow-S1-v0", seeds=seeds, env_kwargs=SHORT, progress=False)
    with pytest.raises(ValueError):
        evaluate_controllers(["PID"], ["S1"], seeds=seeds, progress=False)


def test_numpy_integer_seeds_accepted():
    m = evaluate(ZeroPolicy(), "AUVFollow-S1-v0", seeds=np.array([2]), env_kwargs=SHORT, progress=False)
    assert m["seed"].iloc[0] == 2 and type(m["seed"].iloc[0]) is not bool


def test_tracking_metrics_on_a_hand_computed_array():
    # errors 0.2 at t = 9.95 s and 0.1, 0.3, 0.5 at 10.0 / 10.05 / 10.1 s
    e = np.array([0.2, 0.1, 0.3, 0.5])
    t = 0.05 * np.array([199, 200, 201, 202])
    m = tracking_metrics(e, t, 10.0)
    assert m["full_mean"] == pytest.approx(1.1 / 4)
    assert m["full_rmse"] == pytest.approx(math.sqrt((0.04 + 0.01 + 0.09 + 0.25) / 4))
    assert m["full_max"] == pytest.approx(0.5)
    assert m["steady_mean"] == pytest.approx(0.9 / 3)
    assert m["steady_rmse"] == pytest.approx(math.sqrt(0.35 / 3))
    assert m["steady_max"] == pytest.approx(0.5)


def test_evaluate_controllers_one_scenario_short_episode():
    m = evaluate_controllers(scenarios=["S1"], env_kwargs={"episode_s": 12.0}, progress=False)
    assert list(m["policy"]) == ["PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED"]
    assert (m["scenario"] == "S1").all()
    assert (m["steps"] == 240).all()
    assert np.isfinite(m[list(METRIC_COLUMNS)].to_numpy()).all()


def test_evaluate_controllers_accepts_max_episode_steps():
    m = evaluate_controllers(scenarios=["S1"], env_kwargs=SHORT, progress=False)
    assert list(m["policy"]) == ["PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED"]


def test_evaluate_batched_equals_evaluate():
    pols = [make_controller("PROPOSED", S1_SHORT), make_controller("PID", S1_SHORT), ZeroPolicy()]
    mb = evaluate_batched(pols, "AUVFollow-S1-v0", seeds=[0, 1], env_kwargs=SHORT, progress=False)
    ms = pd.concat([evaluate(make_controller("PROPOSED", S1_SHORT), "AUVFollow-S1-v0", [0, 1],
                             env_kwargs=SHORT, progress=False),
                    evaluate(make_controller("PID", S1_SHORT), "AUVFollow-S1-v0", [0, 1],
                             env_kwargs=SHORT, progress=False),
                    evaluate(ZeroPolicy(), "AUVFollow-S1-v0", [0, 1], env_kwargs=SHORT, progress=False)],
                   ignore_index=True)
    assert list(mb["policy"]) == list(ms["policy"])
    assert list(mb["seed"]) == list(ms["seed"])
    assert list(mb["steps"]) == list(ms["steps"])
    for col in (*METRIC_COLUMNS, "return"):
        np.testing.assert_allclose(mb[col].to_numpy(), ms[col].to_numpy(), rtol=1e-9, atol=1e-12,
                                   err_msg=col)


def _bits(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64).view(np.int64)


@pytest.mark.parametrize("T", [1, 5, 81, 160, 240, 1200, 1201])
def test_batched_metric_rows_equal_tracking_metrics_bit_for_bit(T):
    from controllers.evaluation import _tracking_metrics_rows

    rng = np.random.default_rng(T)
    e = rng.uniform(0.0, 1.0, (T, 7 if T > 240 else 150)) ** 3  # stored (T, m): rows are strided views
    e[T // 2, 3] = np.nan
    times = 0.05 * np.arange(1, T + 1)
    for steady in (0.0, 4.0, 10.0, 1e9):
        rows = _tracking_metrics_rows(e.T, times, steady)
        for i, row in enumerate(rows):
            ref = tracking_metrics(np.ascontiguousarray(e[:, i]), times, steady)
            assert list(row) == list(ref)
            np.testing.assert_array_equal(_bits(list(row.values())), _bits(list(ref.values())), err_msg=f"row {i}")


def test_evaluate_batched_metrics_are_those_of_its_trajectories_bit_for_bit():
    # full-length episodes (computed at once) and early ends (ZeroPolicy drifts off: one by one)
    spec = auv_follow_env.make_task_spec("S4")
    m, t = evaluate_batched([make_controller("PROPOSED", spec), ZeroPolicy()], "AUVFollow-S4-v0", seeds=[0, 1],
                            trajectories=True, progress=False)
    assert m["steps"].iloc[0] == spec.n_steps and m["steps"].iloc[-1] < spec.n_steps
    for (policy, seed), frame in t.groupby(["policy", "seed"], sort=False):
        row = m[(m["policy"] == policy) & (m["seed"] == seed)].iloc[0]
        times = frame["time"].to_numpy()
        for ref, col in (("true", "err_true"), ("own", "err_own")):
            expected = tracking_metrics(frame[col].to_numpy(), times, spec.steady_start_s)
            got = [row[f"{ref}_{k}"] for k in METRIC_KEYS]
            np.testing.assert_array_equal(_bits(got), _bits([expected[k] for k in METRIC_KEYS]),
                                          err_msg=f"{policy} {seed} {ref}")


# --------------------------------------------------------------------------------------------
# paper-level behaviour: without prediction the follower lags the TRUE reference by v_t tau


@pytest.fixture(scope="module")
def s4_full():
    spec = auv_follow_env.make_task_spec("S4")
    return {n: evaluate(make_controller(n, spec), "AUVFollow-S4-v0", seeds=[0], progress=False).iloc[0]
            for n in ("PID", "ROBUST_ONLY", "PROPOSED")}


def test_s4_without_prediction_lags_by_v_tau(s4_full):
    d_tau = 0.52 * 2.0  # Table 2: v_t tau = 1.04 m
    for n in ("PID", "ROBUST_ONLY"):
        assert s4_full[n]["steps"] == 1200
        assert abs(s4_full[n]["true_steady_mean"] - d_tau) <= 0.25 * d_tau, n


def test_s4_prediction_removes_most_of_the_lag(s4_full):
    d_tau = 0.52 * 2.0
    assert s4_full["PROPOSED"]["true_steady_mean"] < 0.3 * d_tau
    # measured against its own (delayed) reference, ROBUST_ONLY does not see the lag
    assert s4_full["ROBUST_ONLY"]["own_steady_mean"] < 0.3 * d_tau


def test_evaluate_refuses_a_controller_built_for_another_task():
    # PROPOSED built for S4 (tau = 2 s) run on S4 with tau = 1 s: delay_s and delay_steps differ
    policy = make_controller("PROPOSED", auv_follow_env.make_task_spec("S4"))
    for run in (lambda: evaluate(policy, "AUVFollow-S4-v0", [0], env_kwargs={"delay_s": 1.0}, progress=False),
                lambda: evaluate_batched([policy], "AUVFollow-S4-v0", [0], env_kwargs={"delay_s": 1.0},
                                         progress=False)):
        with pytest.raises(ValueError, match=r"delay_s: policy 2.0, env 1.0; delay_steps: policy 40, env 20") as e:
            run()
        assert "p_d" not in str(e.value) and "task_spec" in str(e.value)
    other_limits = auv_follow_env.make_task_spec("S1", episode_s=12.0, force_limits=[100.0, 150.0, 30.0])
    with pytest.raises(ValueError, match=r"^policy 'PID' .*force_limits: policy \(100.0, 150.0, 30.0\)"):
        evaluate(make_controller("PID", other_limits), "AUVFollow-S1-v0", [0], env_kwargs=SHORT, progress=False)


def test_evaluate_accepts_a_spec_that_differs_only_in_unused_fields():
    # episode length and scenario name are not used by the controller: S1's spec on AUVFollow-v0 with S1 settings
    spec = auv_follow_env.make_task_spec("S1", episode_s=60.0)
    m = evaluate(make_controller("PID", spec), "AUVFollow-S1-v0", [0], env_kwargs=SHORT, progress=False)
    assert len(m) == 1 and m["steps"].iloc[0] == 240


def test_progress_in_a_log_has_no_nested_bars_or_cursor_codes(capsys):
    # stderr captured by pytest is not a terminal: only the outer bar, no cursor-movement escape codes
    evaluate_controllers(["PID"], scenarios=("S1",), seeds=[0], env_kwargs=SHORT, progress=True)
    err = capsys.readouterr().err
    assert "scenarios" in err  # the outer bar is kept
    assert "policies x" not in err and "\x1b[" not in err


@pytest.mark.parametrize("name", ["PROPOSED_KF_DOB", "MPC"])
def test_estimator_controllers_score_the_same_with_and_without_peek_reuse(name):
    # evaluate_batched peeks through reference() at the observation the next predict() commits;
    # the estimator reuses that peek. Every score must equal the run that recomputes everything.
    import gymnasium as gym

    kw = {"episode_s": 3.0, "steady_start_s": 1.0}
    env_id = "AUVFollow-S4-v0" if name == "MPC" else "AUVFollow-Hard-v1"
    spec = gym.make(env_id, **kw).unwrapped.task_spec
    frames = []
    for reuse in (True, False):
        policy = make_controller(name, spec)
        policy.estimator.reuse_peek = reuse
        frames.append(evaluate_batched([policy], env_id, seeds=range(3), env_kwargs=kw, progress=False))
    pd.testing.assert_frame_equal(frames[0], frames[1], check_exact=True)
