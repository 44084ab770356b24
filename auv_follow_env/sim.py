"""The batched simulator shared by the single env and the vector env.

``BatchSim`` owns the arrays of :mod:`auv_follow_env.dynamics` for N envs, draws each
episode's random parameters from that env's own generator, and calls the kernels. The
Gymnasium shells (``AUVFollowEnv``, ``AUVFollowVectorEnv``) only validate input and
format output.
"""

from __future__ import annotations

import math

import numpy as np

from auv_follow_env import dynamics as dyn
from auv_follow_env.layout import OBS_DIM
from auv_follow_env.params import EnvConfig, VehicleParams

__all__ = ["BatchSim", "param_row", "sample_params", "config_vector"]

TWO_PI = 2.0 * math.pi
#: range of the current's period [s] (ours: "slowly varying", tens of seconds)
CURRENT_PERIOD_RANGE = (40.0, 80.0)


def param_row(*, vehicle: VehicleParams, target_speed: float = 0.0, surge_amp: float = 0.0,
              surge_period: float = 1.0, surge_phase: float = 0.0, yaw_rate_amp: float = 0.0,
              yaw_period: float = 1.0, yaw_phase: float = 0.0,
              current_x: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
              current_y: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
              disturbance: tuple[tuple[float, float, float, float], ...] = ((0.0,) * 4,) * 3,
              ) -> np.ndarray:
    """One row of the kernel's parameter array, from explicit values.

    ``current_x``/``current_y`` are (mean [m/s], amplitude [m/s], omega [rad/s], phase);
    ``disturbance`` is three rows (u, v, r) of (amp1, phase1, amp2, phase2) in N / N m.
    """
    row = np.zeros(dyn.NP)
    row[[dyn.P_M, dyn.P_IZ, dyn.P_XU, dyn.P_YV, dyn.P_NR]] = (
        vehicle.m, vehicle.I_z, vehicle.X_u, vehicle.Y_v, vehicle.N_r)
    row[dyn.P_TV:dyn.P_TPR + 1] = (target_speed, surge_amp, TWO_PI / surge_period, surge_phase,
                                   yaw_rate_amp, TWO_PI / yaw_period, yaw_phase)
    row[dyn.P_CX:dyn.P_CX + 4] = current_x
    row[dyn.P_CY:dyn.P_CY + 4] = current_y
    row[dyn.P_D:dyn.P_D + 12] = np.asarray(disturbance, dtype=np.float64).ravel()
    return row


def sample_params(config: EnvConfig, rng: np.random.Generator) -> np.ndarray:
    """Draw one episode's parameters from ``rng`` (always exactly 12 uniforms, in order).

    Random: the target's two manoeuvre phases, the current's periods and phases, and the
    six disturbance-tone phases. Fixed by the config: everything else.
    """
    u = rng.random(12)
    tp = config.scenario.target
    lvl = config.disturbance
    veh = config.true_vehicle
    lo, hi = CURRENT_PERIOD_RANGE

    def cur(rng_pair: tuple[float, float], up: float, uph: float) -> tuple[float, float, float, float]:
        a, b = rng_pair
        return (0.5 * (a + b), 0.5 * (b - a), TWO_PI / (lo + (hi - lo) * up), TWO_PI * uph)

    scale = (veh.m, veh.m, veh.I_z)  # Table 3 peaks read per unit mass (NOTES.md)
    w1, w2 = dyn.DIST_WEIGHT
    dist = tuple((w1 * pk * sc, TWO_PI * u[6 + 2 * c], w2 * pk * sc, TWO_PI * u[7 + 2 * c])
                 for c, (pk, sc) in enumerate(zip(lvl.peaks, scale, strict=False)))
    return param_row(
        vehicle=veh, target_speed=tp.speed, surge_amp=tp.surge_amp, surge_period=tp.surge_period,
        surge_phase=TWO_PI * u[0], yaw_rate_amp=tp.yaw_rate_amp, yaw_period=tp.yaw_period,
        yaw_phase=TWO_PI * u[1], current_x=cur(lvl.current_x, u[2], u[3]),
        current_y=cur(lvl.current_y, u[4], u[5]), disturbance=dist)


def config_vector(config: EnvConfig) -> np.ndarray:
    """The kernel's static ``cfg`` vector."""
    c = np.zeros(dyn.NC)
    c[dyn.C_DT] = config.dt
    c[dyn.C_NSUB] = config.physics_substeps
    c[dyn.C_D] = config.delay_steps
    c[dyn.C_L] = config.delay_steps + 1
    c[dyn.C_PDX], c[dyn.C_PDY] = config.p_d
    c[dyn.C_PSID] = config.psi_d
    c[dyn.C_FU], c[dyn.C_FV], c[dyn.C_FR] = config.force_limits
    c[dyn.C_MAXD] = config.max_distance_m
    c[dyn.C_NSTEPS] = config.n_steps
    c[dyn.C_EFFORT] = config.effort_weight
    c[dyn.C_INIT] = config.init_offset_m
    return c


class BatchSim:
    """N independent AUVFollow episodes stepped together by the numba kernels."""

    def __init__(self, config: EnvConfig, num_envs: int) -> None:
        self.config = config
        self.num_envs = num_envs
        self.cfg = config_vector(config)
        L = config.delay_steps + 1
        self.state = np.zeros((num_envs, 9))
        self.k = np.zeros(num_envs, dtype=np.int64)
        self.buf = np.zeros((num_envs, L, 6))
        self.params = np.zeros((num_envs, dyn.NP))
        self.obs = np.zeros((num_envs, OBS_DIM), dtype=np.float32)
        self.truth = np.zeros((num_envs, dyn.NT))
        self.err_hist = np.zeros((num_envs, config.n_steps))
        self.rew = np.zeros(num_envs)
        self.term = np.zeros(num_envs, dtype=np.bool_)
        self.sample_times = config.dt * np.arange(1, config.n_steps + 1)

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """New episodes for envs ``idx``, drawing env idx[j]'s parameters from rngs[j]."""
        for i, rng in zip(idx, rngs, strict=True):
            self.params[i] = sample_params(self.config, rng)
        dyn.reset_kernel(self.state, self.k, self.buf, self.params, self.cfg,
                         np.asarray(idx, dtype=np.int64), self.obs, self.truth)

    def step(self, action_flat: np.ndarray) -> int:
        """Advance all envs; returns -1 or the index of an env with a non-finite action."""
        return dyn.step_kernel(self.state, self.k, self.buf, self.params, self.cfg, self.obs,
                               self.truth, self.err_hist, self.rew, self.term, action_flat)

    def step_call(self) -> tuple:
        """(kernel, leading args) so a hot loop can call ``kernel(*args, action_flat)``."""
        return (dyn.step_kernel, (self.state, self.k, self.buf, self.params, self.cfg, self.obs,
                             self.truth, self.err_hist, self.rew, self.term))

    def errors(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(errors, times) recorded so far in env i's episode (post-step samples)."""
        n = min(int(self.k[i]), self.config.n_steps)
        return self.err_hist[i, :n], self.sample_times[:n]
