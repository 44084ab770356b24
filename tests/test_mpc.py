"""The MPC with the thrusters in its model (controllers/mpc.py), in closed loop on the real
kernel through the single env and the vector env.

Expected values are worked out here, not printed by the code under test:

* **Limits.** The plant's thrusters (auv_follow_env.dynamics.thrusters) apply
  ``F_k = F_{k-1} + alpha (a_k L - F_{k-1})``, ``alpha = 1 - exp(-dt / T)``, then clip the change
  to ``rate dt L``. The test replays that model itself from the actions: every action is in
  [-1, 1] and every change ``|alpha (a_k L - F_{k-1})|`` is within ``rate dt L`` (the rate limiter
  never has to act), and both limits are reached at some step (else the test could not fail).
* **Control floor on a straight line.** A target at constant velocity, a perfect link (a fix
  every step, no latency, no noise, no loss), no current or disturbance, damping mismatch
  1.05 and the Hard tier's thrusters. In steady following every signal is constant: the
  unmodelled drag is a constant force, which the disturbance observer estimates exactly (at
  constant velocity its d_meas equals it), the MPC's model (one RK4 step per control step) is
  then exact on the steady trajectory (constant velocities and heading, positions linear in
  time: RK4 integrates them without error) and the thrusters hold a constant force (no lag
  left). So the floor is zero error up to rounding and the slowest closed-loop transient:
  we require < 1e-6 m over the last 10 s of a 40 s run (measured: about 1e-8 m). The same run
  without the actuator model must be far off (> 0.1 m): the test discriminates.
* **Batching.** Each env's problem is solved alone (per-env ADMM penalty, every product per
  env, no quantity shared across the batch), so a batch of envs gives each env bit for bit
  the actions it gets alone.
* **ADMM.** Run long, the batched kernel reaches the optimum of an independent exact solver
  (CasADi's active-set qrqp) on the MPC's own constraint matrix.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401
from auv_follow_env import dynamics as dyn
from auv_follow_env.params import make_task_spec
from controllers import make_controller
from controllers.mpc import MPCConfig, MPCController, thruster_coefficients

HARD_TC, HARD_RATE = 0.3, 1.5  # the Hard tier's thrusters (docs/tiers.md): lag [s], rate [1/s]
PERFECT_LINK = dict(update_period_s=0.05, latency_s=0.0, latency_spread_s=0.0, loss_prob=0.0,
                    burst_p_good_bad=0.0, fix_sigma_m=0.0, fix_sigma_per_m=0.0, heading_sigma_rad=0.0,
                    velocity_sigma_mps=0.0, yaw_rate_sigma_radps=0.0)
STRAIGHT = dict(disturbance="L0", target_speed=0.5, target_surge_amp=0.0, target_yaw_rate_amp=0.0,
                target_speed_std=0.0, target_yaw_rate_std=0.0)


def run(env, policy, seed=0):
    """One episode; returns actions (T, 3), the plant's applied forces (T, 3) and errors (T,)."""
    obs, _ = env.reset(seed=seed)
    sim = env.unwrapped._sim
    acts, applied, errs, pred = [], [], [], []
    done, k = False, 0
    while not done:
        a, _ = policy.predict(obs, episode_start=np.array([k == 0]))
        obs, rew, term, trunc, _ = env.step(a)
        acts.append(np.asarray(a, dtype=np.float64))
        applied.append(sim.proc[0, dyn.R_F:dyn.R_F + 3].copy())
        pred.append(policy.applied_force[0].copy())
        errs.append(-rew)
        done, k = term or trunc, k + 1
    return np.asarray(acts), np.asarray(applied), np.asarray(errs), np.asarray(pred)


def test_task_spec_states_the_thrusters_of_v1_and_none_on_v0():
    for tier in ("Easy", "Medium", "Hard", "Extreme"):
        env = gym.make(f"AUVFollow-{tier}-v1")
        env.reset(seed=0)
        row = env.unwrapped._sim.params[0]
        alpha, step = thruster_coefficients(env.unwrapped.task_spec)
        assert alpha == pytest.approx(row[dyn.P_TH_ALPHA], rel=1e-15)  # what the plant applies
        assert step == row[dyn.P_TH_RATE] or (math.isinf(step) and math.isinf(row[dyn.P_TH_RATE]))
    spec = gym.make("AUVFollow-Hard-v1").unwrapped.task_spec
    assert (spec.thruster_tc_s, spec.thruster_rate) == (HARD_TC, HARD_RATE)
    s4 = gym.make("AUVFollow-S4-v0").unwrapped.task_spec
    assert s4.thruster_tc_s == 0.0 and math.isinf(s4.thruster_rate)
    assert thruster_coefficients(s4) == (1.0, math.inf)


def test_mpc_respects_force_and_rate_limits_at_every_step():
    limits = [40.0, 40.0, 8.0]  # tight, so that the start saturates the force as well as the rate
    env = gym.make("AUVFollow-v1", episode_s=8.0, steady_start_s=4.0, force_limits=limits, thruster_tc_s=HARD_TC,
                   thruster_rate=HARD_RATE, **PERFECT_LINK, **STRAIGHT)
    mpc = MPCController(env.unwrapped.task_spec)
    acts, applied, _, pred = run(env, mpc)
    L = np.asarray(limits)
    alpha = 1.0 - math.exp(-0.05 / HARD_TC)
    F = np.zeros(3)
    changes = []
    for a in acts:  # the plant's lag, replayed here without its rate clip
        step = alpha * (a * L - F)
        changes.append(np.abs(step) / L)
        F = F + step
    changes = np.asarray(changes)
    assert np.all(np.abs(acts) <= 1.0)
    assert np.all(changes <= HARD_RATE * 0.05 * (1 + 1e-9))
    assert np.any(np.abs(acts) >= 1.0 - 1e-6)  # the force limit is reached ...
    assert np.any(changes >= HARD_RATE * 0.05 * (1 - 1e-3))  # ... and the rate limit
    np.testing.assert_allclose(applied, pred, rtol=0, atol=1e-9 * L.max())  # the observer is told what is applied


@pytest.mark.parametrize("actuator_model", [True, False])
def test_mpc_tracks_a_straight_line_to_the_control_floor(actuator_model):
    env = gym.make("AUVFollow-v1", episode_s=40.0, steady_start_s=30.0, mismatch=1.05, thruster_tc_s=HARD_TC,
                   thruster_rate=HARD_RATE, **PERFECT_LINK, **STRAIGHT)
    mpc = MPCController(env.unwrapped.task_spec, MPCConfig(actuator_model=actuator_model))
    _, _, err, _ = run(env, mpc)
    assert err[0] > 0.5  # starts 0.87 m behind
    if actuator_model:
        assert np.max(err[-200:]) < 1e-6
    else:
        assert np.mean(err[-200:]) > 0.1  # without the thrusters in its model it oscillates


def test_batched_mpc_equals_each_env_run_alone():
    kw = dict(episode_s=4.0, steady_start_s=2.0)
    seeds = [500, 501, 502]
    venv = gym.make_vec("AUVFollow-Hard-v1", num_envs=len(seeds), **kw)
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    batched = MPCController(spec)
    obs, _ = venv.reset(seed=seeds)
    acts_b = []
    for k in range(80):
        a, _ = batched.predict(obs, episode_start=np.full(len(seeds), k == 0))
        acts_b.append(a)
        obs, *_ = venv.step(a)
    venv.close()
    acts_b = np.asarray(acts_b)
    for j, s in enumerate(seeds):
        env = gym.make("AUVFollow-Hard-v1", **kw)
        alone = MPCController(spec)
        obs, _ = env.reset(seed=s)
        for k in range(80):
            a, _ = alone.predict(obs, episode_start=np.array([k == 0]))
            np.testing.assert_array_equal(a, acts_b[k, j])
            obs, *_ = env.step(a)


def test_admm_converges_to_the_exact_qp_solution():
    """The batched ADMM kernel, run long, reaches the optimum that CasADi's active-set solver
    (qrqp, an independent exact method) finds for the same QP: the MPC's own constraint matrix
    (force and rate rows of the Hard thrusters) and a random convex cost pushing the commands
    past their limits (so constraints are active)."""
    import casadi as ca

    from controllers.mpc import _admm, _factor

    spec = make_task_spec("S4", version="v1", thruster_tc_s=HARD_TC, thruster_rate=HARD_RATE)
    mpc = MPCController(spec, MPCConfig(horizon_s=0.75, intervals=5))
    A, Rb = mpc._A, mpc._Rb
    nv, nc = A.shape[1], A.shape[0]
    rng = np.random.default_rng(0)
    n = 3
    J = rng.normal(size=(n, 2 * nv, nv))
    H = J.transpose(0, 2, 1) @ J
    q = rng.normal(scale=20.0, size=(n, nv))
    F0 = rng.uniform(-0.5, 0.5, size=(n, 3))
    lo, hi = np.full((n, nc), -1.0), np.full((n, nc), 1.0)
    base = mpc._rate_f0[None, :] * np.tile(F0, (1, 5))
    band = mpc.rate_step / mpc.alpha
    lo[:, nv:], hi[:, nv:] = base - band, base + band
    x, z, y = np.zeros((n, nv)), np.zeros((n, nc)), np.zeros((n, nc))
    rho = np.full((n, nc), 1.0)
    sigma = np.full(n, 1e-6)
    L = np.empty_like(H)
    _factor(H, np.zeros((nv, nv)), Rb, rho, sigma, L)
    _admm(L, q, Rb, lo, hi, x, z, y, rho, sigma, 20000, 1.6)
    qp = ca.conic("qp", "qrqp", {"h": ca.DM(H[0]).sparsity(), "a": ca.DM(A).sparsity()},
                  {"print_iter": False, "print_header": False, "print_info": False})
    active = 0
    for i in range(n):
        sol = qp(h=H[i], g=q[i], a=A, lba=lo[i], uba=hi[i])
        exact = np.asarray(sol["x"]).ravel()
        Ax = A @ exact
        active += int(np.sum((Ax <= lo[i] + 1e-9) | (Ax >= hi[i] - 1e-9)))
        np.testing.assert_allclose(x[i], exact, atol=1e-6)
    assert active > 0


def test_registered_mpc_is_this_controller_with_the_tier_thrusters():
    spec = make_task_spec("S4", version="v1", tier=None, thruster_tc_s=0.2, thruster_rate=2.0)
    mpc = make_controller("MPC", spec)
    assert isinstance(mpc, MPCController)
    assert mpc.alpha == pytest.approx(1.0 - math.exp(-0.05 / 0.2))
    assert mpc.rate_step == pytest.approx(0.1)


@pytest.mark.parametrize("kwargs, name", [({"horizon_s": 0.0}, "horizon_s"), ({"intervals": 0}, "intervals"),
                                          ({"admm_iterations": 1.5}, "admm_iterations"), ({"w_pos": -1.0}, "w_pos"),
                                          ({"admm_rho": 0.0}, "admm_rho"), ({"actuator_model": 1}, "actuator_model"),
                                          ({"w_force": 0.0, "w_rate": 0.0}, "w_force")])
def test_mpc_config_rejects_bad_values(kwargs, name):
    with pytest.raises(ValueError, match=name):
        MPCConfig(**kwargs)


def test_mpc_rejects_a_horizon_that_is_not_whole_blocks_of_control_steps():
    with pytest.raises(ValueError, match="horizon_s=3.01"):
        MPCController(make_task_spec("S4"), MPCConfig(horizon_s=3.01))
