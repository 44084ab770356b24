"""Delay-aware nonlinear MPC on the nominal model (ours, not the paper's).

One more composition over the same target estimator (:mod:`controllers.estimator`) and the
nominal model of the task spec (ARCHITECTURE.md, point 10):

* **reference**: the estimator's predicted target trajectory over the horizon (from the
  newest delayed fix, propagated past the present), turned into the reference point of
  eq. (21), ``p_ref(t) = p_t(t) + R(psi_t(t)) p_d``, ``psi_ref = psi_t + psi_d``, and its
  velocity (by central differences of the predicted trajectory);
* **model**: eqs. (3)-(9) with the *nominal* m, I_z, X_u, Y_v, N_r, the measured current held
  constant in the inertial frame, and (``disturbance_observer``, default on) the inner-loop
  disturbance observer's estimate as a constant body-frame force: offset-free MPC, so that
  the damping mismatch does not leave a steady offset;
* **problem**: multiple shooting, ``intervals`` RK4 steps of ``horizon_s / intervals``, controls
  piecewise constant and normalised by the force limits, **bounded to [-1, 1]** (the force
  limits are hard constraints); least-squares cost on position, heading, velocity and yaw-rate
  errors to the reference, force and force-rate, with a heavier terminal stage;
* **solver**: a Gauss-Newton SQP (``sqp_iterations`` iterations per control step; 1 = the
  real-time iteration of Diehl et al.) whose QPs CasADi's ``qrqp`` active-set solver solves;
  warm-started from the previous step's solution and multipliers (the control step, 0.05 s,
  is shorter than a shooting interval, so the nodes are kept and only x0 is replaced). Timing on this
  machine: ``experiments/bench_mpc.py`` -> ``results/bench_mpc.md``.

Everything is in the estimator's odometry frame (compass-aligned), with the follower's
heading unwrapped across +-pi, so the warm start stays valid from step to step.
Without a target fix yet (v1, ``has_packet`` = 0) the reference is the follower's own pose at
that step (hold position).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from auv_follow_env.layout import decode
from auv_follow_env.params import TaskSpec
from controllers.base import ScriptedPolicy
from controllers.disturbance import DisturbanceObserver
from controllers.estimator import EstimatorConfig, TargetEstimator

__all__ = ["MPCConfig", "MPCController"]

NX, NU = 6, 3


@dataclass(frozen=True, kw_only=True)
class MPCConfig:
    """Settings of :class:`MPCController` (all ours). w_pos and w_vel were picked among
    (10, 1), (30, 1), (10, 0.3), (30, 0.3), (10, 3), (3, 1) and a 2 s horizon by the
    steady-state true-reference error on seeds 100-109 of S4 (and S2); the others are
    first guesses, left as they were."""

    horizon_s: float = 3.0  #: prediction horizon [s]
    intervals: int = 20  #: shooting intervals over the horizon (RK4 step = horizon_s / intervals)
    sqp_iterations: int = 2  #: Gauss-Newton SQP iterations per control step (1 = RTI)
    w_pos: float = 30.0  #: weight on the position error [1/m^2]
    w_psi: float = 1.0  #: weight on the heading error [1/rad^2]
    w_vel: float = 0.3  #: weight on the inertial velocity error to the reference's [s^2/m^2]
    w_r: float = 0.1  #: weight on the yaw-rate error [s^2/rad^2]
    w_force: float = 1e-3  #: weight on the normalised force (force / limit) [-]
    w_rate: float = 1e-2  #: weight on the change of the normalised force between intervals [-]
    w_terminal: float = 5.0  #: multiplier of the state weights at the last node [-]
    qp_solver: str = "osqp"  #: CasADi conic plugin for the SQP's QPs: "osqp" or "qrqp"
    disturbance_observer: bool = True  #: add the disturbance observer's estimate to the model
    dob_time_constant: float = 0.5  #: its low-pass time constant [s]

    def __post_init__(self) -> None:
        def num(name: str, lo: float, strict: bool) -> None:
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (
                v > lo if strict else v >= lo)
            if not ok:
                raise ValueError(f"{name}={v!r} is invalid: must be a finite number {'>' if strict else '>='} {lo}")

        if self.qp_solver not in ("osqp", "qrqp"):
            raise ValueError(f"qp_solver={self.qp_solver!r} is invalid: must be 'osqp' or 'qrqp'")
        num("horizon_s", 0.0, True)
        for n in ("w_pos", "w_psi", "w_vel", "w_r", "w_force", "w_rate"):
            num(n, 0.0, False)
        num("w_terminal", 0.0, True)
        num("dob_time_constant", 0.0, True)
        for n, lo in (("intervals", 1), ("sqp_iterations", 1)):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"{n}={v!r} is invalid: must be an integer >= {lo}")
        if self.w_force + self.w_rate <= 0:
            raise ValueError(f"w_force={self.w_force!r} and w_rate={self.w_rate!r} are invalid: at least one "
                             f"must be > 0 (the QP needs a regularised force)")


def _build(spec: TaskSpec, cfg: MPCConfig):
    """CasADi functions of one MPC problem: QP data of the Gauss-Newton linearisation and the
    QP solver. Parameters p = [x0 (6), current (2, inertial), d_hat (3, body), u_prev (3),
    reference (N x 6: x, y, psi, vx, vy, r)]."""
    nom = spec.nominal
    lim = np.asarray(spec.force_limits, dtype=np.float64)
    N = cfg.intervals
    h = cfg.horizon_s / N
    x = ca.SX.sym("x", NX)
    u = ca.SX.sym("u", NU)
    c = ca.SX.sym("c", 5)  # current (inertial x, y), d_hat (body u, v, r)

    def f(x, u, c):
        ps, uu, vv, r = x[2], x[3], x[4], x[5]
        cs, sn = ca.cos(ps), ca.sin(ps)
        ur = uu - (cs * c[0] + sn * c[1])  # eqs. (5), (9)
        vr = vv - (-sn * c[0] + cs * c[1])
        F = u * lim
        return ca.vertcat(cs * uu - sn * vv, sn * uu + cs * vv, r,  # eq. (3)
                          (F[0] - nom.X_u * ur + nom.m * vv * r + c[2]) / nom.m,  # eqs. (6)-(8)
                          (F[1] - nom.Y_v * vr - nom.m * uu * r + c[3]) / nom.m,
                          (F[2] - nom.N_r * r + c[4]) / nom.I_z)

    k1 = f(x, u, c)
    k2 = f(x + h / 2 * k1, u, c)
    k3 = f(x + h / 2 * k2, u, c)
    k4 = f(x + h * k3, u, c)
    step = ca.Function("rk4", [x, u, c], [x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])

    X = ca.SX.sym("X", NX, N + 1)
    U = ca.SX.sym("U", NU, N)
    x0 = ca.SX.sym("x0", NX)
    cc = ca.SX.sym("cc", 5)
    u_prev = ca.SX.sym("u_prev", NU)
    ref = ca.SX.sym("ref", 6, N)
    g = [X[:, 0] - x0]
    res = []
    sq = math.sqrt
    for k in range(N):
        g.append(X[:, k + 1] - step(X[:, k], U[:, k], cc))
        xs, rk = X[:, k + 1], ref[:, k]
        wt = sq(cfg.w_terminal) if k == N - 1 else 1.0
        cs, sn = ca.cos(xs[2]), ca.sin(xs[2])
        res += [wt * sq(cfg.w_pos) * (xs[0] - rk[0]), wt * sq(cfg.w_pos) * (xs[1] - rk[1]),
                wt * sq(cfg.w_psi) * (xs[2] - rk[2]),
                wt * sq(cfg.w_vel) * (cs * xs[3] - sn * xs[4] - rk[3]),
                wt * sq(cfg.w_vel) * (sn * xs[3] + cs * xs[4] - rk[4]),
                wt * sq(cfg.w_r) * (xs[5] - rk[5])]
        res += [sq(cfg.w_force) * U[i, k] for i in range(NU)]
        prev = u_prev if k == 0 else U[:, k - 1]
        res += [sq(cfg.w_rate) * (U[i, k] - prev[i]) for i in range(NU)]
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    p = ca.vertcat(x0, cc, u_prev, ca.vec(ref))
    r = ca.vertcat(*res)
    gg = ca.vertcat(*g)
    Jr = ca.jacobian(r, w)
    H = ca.mtimes(Jr.T, Jr) + 1e-6 * ca.DM.eye(int(w.shape[0]))  # strictly convex QP (X0 has no cost)
    qp_data = ca.Function("qp_data", [w, p], [H, ca.mtimes(Jr.T, r), gg, ca.jacobian(gg, w)])
    Hs = ca.Function("hs", [w, p], [H]).sparsity_out(0)
    As = ca.Function("as", [w, p], [ca.jacobian(gg, w)]).sparsity_out(0)
    if cfg.qp_solver == "qrqp":
        opts = {"print_iter": False, "print_header": False, "print_info": False, "error_on_fail": False}
    else:
        opts = {"osqp": {"verbose": False, "eps_abs": 1e-7, "eps_rel": 1e-7, "max_iter": 4000, "polish": True},
                "warm_start_primal": True, "warm_start_dual": True, "error_on_fail": False}
    qp = ca.conic("mpc_qp", cfg.qp_solver, {"h": Hs, "a": As}, opts)
    return qp_data, qp, int(w.shape[0]), int(gg.shape[0]), h


class MPCController(ScriptedPolicy):
    """Delay-aware nonlinear MPC (see the module docstring), batched over N envs (one
    warm-started problem per env; ``solve_times`` keeps the wall time of each env-step's solve).

    Args:
        spec: the env's TaskSpec.
        config: :class:`MPCConfig`.
        estimator_config: the target estimator's settings (default: as ``PROPOSED_KF``).
        name: label used in tables.
    """

    name = "MPC"

    def __init__(self, spec: TaskSpec, config: MPCConfig | None = None,
                 estimator_config: EstimatorConfig | None = None, name: str = "MPC") -> None:
        super().__init__(spec)
        if config is not None and not isinstance(config, MPCConfig):
            raise ValueError(f"config={config!r} is invalid: must be an MPCConfig or None")
        self.config = config if config is not None else MPCConfig()
        self.name = name
        self.estimator = TargetEstimator(spec, estimator_config)
        self.dob = (DisturbanceObserver(spec.nominal, spec.dt, spec.force_limits, self.config.dob_time_constant)
                    if self.config.disturbance_observer else None)
        self._qp_data, self._qp, self._nw, self._ng, self._h = _build(spec, self.config)
        N = self.config.intervals
        self._nxw = NX * (N + 1)
        self._lb = np.full(self._nw, -np.inf)
        self._ub = np.full(self._nw, np.inf)
        self._lb[self._nxw:] = -1.0  # force limits, normalised: hard bounds
        self._ub[self._nxw:] = 1.0
        self._times = self._h * np.arange(0, N + 2)  # reference samples incl. one either side
        self._W: np.ndarray | None = None
        self._lam_a: np.ndarray | None = None
        self._lam_x: np.ndarray | None = None
        self._psi_unwrapped: np.ndarray | None = None
        self._u_prev: np.ndarray | None = None
        self.solve_times: list[float] = []
        #: the first control of each env's last QP solution, before the safety clip (N, 3),
        #: normalised by the force limits: what the constraints themselves gave
        self.last_solution: np.ndarray | None = None

    # ------------------------------------------------------------------------------------
    def _references(self, valid: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """(N_env, horizon, 6): reference point pose and velocity at the horizon's nodes."""
        px, py, ps = self.estimator.trajectory(self._times, frame="odometry")
        pdx, pdy = self.spec.p_d
        c, s = np.cos(ps), np.sin(ps)
        rx, ry = px + c * pdx - s * pdy, py + s * pdx + c * pdy
        # reference heading near the follower's unwrapped heading
        rpsi = ps + self.spec.psi_d
        k = np.round((x0[:, 2] - rpsi[:, 1]) / (2 * math.pi))
        rpsi = rpsi + 2 * math.pi * k[:, None]
        h = self._h
        vx, vy, vr = ((a[:, 2:] - a[:, :-2]) / (2 * h) for a in (rx, ry, rpsi))
        ref = np.stack([rx[:, 1:-1], ry[:, 1:-1], rpsi[:, 1:-1], vx, vy, vr], axis=-1)
        hold = ~valid
        if hold.any():
            ref[hold] = 0.0
            ref[hold, :, 0] = x0[hold, 0, None]
            ref[hold, :, 1] = x0[hold, 1, None]
            ref[hold, :, 2] = x0[hold, 2, None]
        return ref

    def reference(self, observation) -> np.ndarray:
        obs = np.atleast_2d(np.asarray(observation, dtype=np.float64))
        est = self.estimator.step(obs, None, commit=False, with_cov=False)
        pdx, pdy = self.spec.p_d
        c, s = np.cos(est.rel_psi), np.sin(est.rel_psi)
        ref = np.stack([est.rel_x + c * pdx - s * pdy, est.rel_y + s * pdx + c * pdy,
                        est.rel_psi + self.spec.psi_d], axis=-1)
        ref[~est.valid] = 0.0
        return ref

    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        o = decode(obs)
        n = obs.shape[0]
        est = self.estimator.step(obs, reset_mask, with_cov=False)
        odom, psi_f = self.estimator.follower_odometry()
        if self._W is None or self._W.shape[0] != n:
            self._W = np.zeros((n, self._nw))
            self._lam_a = np.zeros((n, self._ng))
            self._lam_x = np.zeros((n, self._nw))
            self._psi_unwrapped = psi_f.copy()
            self._u_prev = np.zeros((n, NU))
            reset_mask = np.ones(n, dtype=bool)
        dpsi = psi_f - self._psi_unwrapped
        self._psi_unwrapped = np.where(reset_mask, psi_f, self._psi_unwrapped + np.arctan2(np.sin(dpsi), np.cos(dpsi)))
        x0 = np.column_stack([odom, self._psi_unwrapped, o["u"], o["v"], o["r"]])
        cur = np.column_stack([np.cos(psi_f) * o["current_u"] - np.sin(psi_f) * o["current_v"],
                               np.sin(psi_f) * o["current_u"] + np.cos(psi_f) * o["current_v"]])
        if self.dob is not None:
            nu = np.column_stack([o["u"], o["v"], o["r"]])
            d_hat = self.dob.update(nu, np.column_stack([o["current_u"], o["current_v"]]), reset_mask)
        else:
            d_hat = np.zeros((n, 3))
        refs = self._references(est.valid, x0)
        N = self.config.intervals
        out = np.zeros((n, NU))
        raw = np.zeros((n, NU))
        for i in range(n):
            t0 = time.perf_counter()
            W = self._W[i]
            if reset_mask[i]:
                W[:self._nxw] = np.tile(x0[i], N + 1)
                W[self._nxw:] = 0.0
                self._lam_a[i] = 0.0
                self._lam_x[i] = 0.0
                self._u_prev[i] = 0.0
            else:  # warm start: the previous solution with the new initial state
                W[:NX] = x0[i]
            p = np.concatenate([x0[i], cur[i], d_hat[i], self._u_prev[i], refs[i].ravel()])
            for _ in range(self.config.sqp_iterations):
                H, q, g, A = self._qp_data(W, p)
                sol = self._qp(h=H, g=q, a=A, lba=-np.asarray(g), uba=-np.asarray(g),
                               lbx=self._lb - W, ubx=self._ub - W, lam_a0=self._lam_a[i], lam_x0=self._lam_x[i])
                W += np.asarray(sol["x"]).ravel()
                self._lam_a[i] = np.asarray(sol["lam_a"]).ravel()
                self._lam_x[i] = np.asarray(sol["lam_x"]).ravel()
            raw[i] = W[self._nxw:self._nxw + NU]
            np.clip(W[self._nxw:], -1.0, 1.0, out=W[self._nxw:])  # safety only: the QP's bounds hold
            u0 = W[self._nxw:self._nxw + NU].copy()
            out[i] = u0
            self._u_prev[i] = u0
            self.solve_times.append(time.perf_counter() - t0)
        self.last_solution = raw
        F = out * self._limits
        if self.dob is not None:
            self.dob.applied(F)
        return F
