"""Our baselines in closed loop on the real kernel: PROPOSED_KF(_DOB) and the MPC following a
straight-line target (a custom parameter row of ``auv_follow_env.sim``), with the analytic
steady offset of the paper's law, the registry, and the MPC's force limits.

Analytic offset of the hierarchical law in steady following of a straight target at speed
v with true surge damping X_u (1 + mm): the inner loop balances the unmodelled drag,
K_u e_u + rho_u sat(e_u / phi_u) = mm X_u v, so e_u = mm X_u v / (K_u + rho_u / phi_u) inside the
boundary layer (|e_u| <= phi_u) and e_u = (mm X_u v - rho_u) / K_u outside it; the outer loop
then leaves ||e_p|| = e_u / K_p. In S4 (mm = 1.05, v = 0.5 m/s) the first formula gives
0.0525 m/s > phi_u = 0.04 m/s, so the second holds: 0.0775 m.
"""

from __future__ import annotations

import numpy as np
import pytest

from auv_follow_env import dynamics as dyn
from auv_follow_env.params import make_config
from auv_follow_env.sim import BatchSim, param_row
from controllers import ALL_CONTROLLERS, CONTROLLERS, EXTENDED_CONTROLLERS, Gains, make_controller
from controllers.mpc import MPCConfig, MPCController

SPEED = 0.5  # m/s


def straight_line_run(policy, config, steps: int):
    """Run ``policy`` on one env whose target moves straight at SPEED; returns errors and forces."""
    sim = BatchSim(config, 1)
    sim.params[0] = param_row(vehicle=config.true_vehicle, target_speed=SPEED, latency_steps=config.delay_steps)
    dyn.reset_kernel(sim.state, sim.k, sim.proc, sim.queue, sim.rs, sim.params, sim.cfg, np.zeros(1, dtype=np.int64),
                     np.zeros(1, dtype=np.int64), np.zeros(1), sim.obs, sim.truth)
    err, forces, raw = [], [], []
    start = np.ones(1, dtype=bool)
    for _ in range(steps):
        a, _ = policy.predict(sim.obs.copy(), episode_start=start)
        start = np.zeros(1, dtype=bool)
        forces.append(np.asarray(a, dtype=np.float64).reshape(3) * np.asarray(config.force_limits))
        if isinstance(policy, MPCController):
            raw.append(policy.last_solution[0].copy())
        assert sim.step(np.asarray(a, dtype=np.float64).ravel()) == -1
        err.append(sim.truth[0, dyn.T_ERR])
    return np.asarray(err), np.asarray(forces), np.asarray(raw)


def test_registry_keeps_the_paper_four_and_lists_ours_apart():
    assert CONTROLLERS == ("PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED")
    assert EXTENDED_CONTROLLERS == ("PROPOSED_KF", "PROPOSED_KF_DOB", "MPC", "PROPOSED_IMM_DOB")
    assert ALL_CONTROLLERS == CONTROLLERS + EXTENDED_CONTROLLERS
    with pytest.raises(ValueError, match="MPC"):
        make_controller("LQR", make_config("S4").task_spec())


def test_proposed_keeps_the_analytic_offset_and_the_observer_removes_it():
    cfg = make_config("S4", "L0")  # mismatch 1.05, tau = 2 s, no current or disturbance
    spec = cfg.task_spec()
    g = Gains()
    drag = cfg.mismatch * spec.nominal.X_u * SPEED  # unmodelled drag [N]
    e_u = drag / (g.K_u + g.rho[0] / g.phi[0])
    if e_u > g.phi[0]:  # outside the boundary layer: the robust term is saturated
        e_u = (drag - g.rho[0]) / g.K_u
    offset = e_u / g.K_p
    assert offset == pytest.approx(0.0775)
    e_prop, _, _ = straight_line_run(make_controller("PROPOSED", spec), cfg, 1200)
    e_kf, _, _ = straight_line_run(make_controller("PROPOSED_KF", spec), cfg, 1200)
    e_dob, _, _ = straight_line_run(make_controller("PROPOSED_KF_DOB", spec), cfg, 1200)
    assert e_prop[-1] == pytest.approx(offset, rel=1e-4)
    assert e_kf[-1] == pytest.approx(offset, rel=1e-4)  # the filter predicts a straight line exactly
    assert e_dob[-1] < 1e-5
    assert np.all(e_dob[-200:] < 1e-4)


def test_mpc_converges_to_a_straight_line_reference_on_the_nominal_plant():
    cfg = make_config("S4", "L0", mismatch=0.0, episode_s=30.0)
    spec = cfg.task_spec()
    mpc = MPCController(spec, MPCConfig(horizon_s=2.0, intervals=10, disturbance_observer=False))
    err, _, _ = straight_line_run(mpc, cfg, cfg.n_steps)
    assert err[0] > 0.5  # starts 0.87 m behind the delayed reference, further from the true one
    assert err[-1] < 1e-3
    assert np.all(err[-100:] < 2e-3)


def test_mpc_respects_the_force_limits_on_every_step():
    """Tight limits (20 N, 20 N, 4 N m) so the start saturates: the applied forces stay within
    the limits at every step and reach them (ADMM's own convergence: tests/test_mpc.py)."""
    cfg = make_config("S4", "L2", force_limits=[20.0, 20.0, 4.0], episode_s=10.0,
                      steady_start_s=5.0)  # a list: params rejects a tuple here
    spec = cfg.task_spec()
    mpc = MPCController(spec, MPCConfig(horizon_s=2.0, intervals=10))
    _, forces, _ = straight_line_run(mpc, cfg, cfg.n_steps)
    assert np.all(np.abs(forces) <= np.asarray(cfg.force_limits) * (1 + 1e-6))
    assert np.any(np.abs(forces) >= np.asarray(cfg.force_limits) * (1 - 1e-6))  # the limits are active


def test_mpc_rejects_a_bad_config_object():
    with pytest.raises(ValueError, match="config"):
        MPCController(make_config("S4").task_spec(), {"horizon_s": 1.0})


@pytest.mark.parametrize("name", EXTENDED_CONTROLLERS)
def test_our_controllers_can_be_the_base_of_a_residual_agent(name):
    """With a zero residual the wrapper applies exactly what the base controller, run on the
    same raw observations, commands; the CLI offers our controllers as bases and in compare."""
    import gymnasium as gym

    from agents.cli import build_parser
    from agents.training.residual import ResidualWrapper

    env = ResidualWrapper(gym.make("AUVFollow-S4-v0", episode_s=1.0, steady_start_s=0.5), controller=name)
    obs, _ = env.reset(seed=0)
    base = make_controller(name, env.unwrapped.task_spec)
    for k in range(8):
        expected, _ = base.predict(obs[:16], episode_start=np.array([k == 0]))
        obs, _, _, _, info = env.step(np.zeros(3))
        np.testing.assert_array_equal(info["applied_action"], expected.astype(np.float64))
    assert build_parser().parse_args(["train", "--controller", name]).controller == name
    assert name in build_parser().parse_args(["compare"]).controllers
