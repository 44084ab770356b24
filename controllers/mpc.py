"""Delay-aware MPC with the thrusters in its model (ours, not the paper's), batched over envs.

One more composition over the same target estimator (:mod:`controllers.estimator`) and the
nominal model of the task spec (ARCHITECTURE.md, point 10):

* **reference**: the estimator's predicted target trajectory over the horizon (from the
  newest delayed fix, propagated past the present), turned into the reference point of
  eq. (21), ``p_ref(t) = p_t(t) + R(psi_t(t)) p_d``, ``psi_ref = psi_t + psi_d``, and its
  velocity (by central differences of the predicted trajectory);
* **model**: eqs. (3)-(9) with the *nominal* m, I_z, X_u, Y_v, N_r, the measured current held
  constant in the inertial frame, the disturbance observer's estimate as a constant body-frame
  force (offset-free MPC), and **the thrusters** as the task spec states them
  (``thruster_tc_s``, ``thruster_rate``; none on v0): the applied force (normalised by the
  force limits) follows the command through the plant's own discrete lag,
  ``F_k = F_{k-1} + alpha (c_k - F_{k-1})``, ``alpha = 1 - exp(-dt / T)``, and is a state of the
  model, started from the force the model predicts from the MPC's own past commands;
* **constraints**: commands held over ``intervals`` blocks of ``horizon_s / intervals``
  (whole control steps), ``|c| <= 1`` (the force limits) and the rate limit
  ``|alpha (c_b - F_b)| <= rate dt`` on the first step of every block (``F_b``: the applied
  force before it; within a block the change only shrinks, by ``1 - alpha`` a step), so the
  plant's rate limiter never clips and the lag model stays exact (linear in the commands);
* **cost**: least squares on position, heading, inertial velocity and yaw-rate errors to the
  reference at the end of every block (the last one ``w_terminal`` times heavier), on the
  command and on its change between blocks (the first block's against the command applied at
  the last step);
* **solver** (one real-time Gauss-Newton iteration per control step, batched over all envs):
  the model is simulated from the present state along the previous step's command sequence
  (RK4, one step per control step) with its exact sensitivities to the commands (the RK4
  step's chain rule, :func:`_linearize`), condensed into a dense QP in the commands alone
  (``3 intervals`` variables), and the QP is solved for every env at once by ADMM (OSQP's
  iteration, :func:`_admm`: ``admm_iterations``, warm-started from the previous step, one
  Cholesky factorisation per env and step, :func:`_factor`); an env whose episode starts (no
  warm start) or whose solution is still outside its constraints by more than 1e-3 (a packet
  moved the reference) gets ten times the iterations, the others not. The first command is
  finally clipped to the exact feasible interval of the first step (force and rate limit given
  the applied force), so the limits hold at every step whatever ADMM's residual;
  ``last_violation`` keeps how far ADMM's own solution was outside its constraints before that
  clip (``experiments/bench_mpc.py`` reports it).

The previous MPC (multiple shooting, CasADi's osqp per env, no actuator in its model) stays as
:class:`CasadiMPCController` for comparison (``experiments/bench_mpc.py``); it is not
registered. Everything is in the estimator's odometry frame (compass-aligned), with the
follower's heading unwrapped across +-pi. Without a target fix yet (v1, ``has_packet`` = 0)
the reference is the follower's own pose at that step (hold position).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numba import njit

from auv_follow_env.layout import decode
from auv_follow_env.params import TaskSpec
from controllers.base import ScriptedPolicy
from controllers.disturbance import DisturbanceObserver
from controllers.estimator import EstimatorConfig, TargetEstimator

__all__ = ["MPCConfig", "MPCController", "CasadiMPCConfig", "CasadiMPCController", "thruster_coefficients"]


#: the largest accepted value of a setting (far beyond use; a bound keeps a typo such as 1e308 from a NaN
#: action or a huge allocation): weights and multipliers, horizons [s], counts
_MAX_WEIGHT, _MAX_SECONDS, _MAX_COUNT = 1e6, 600.0, 10_000


def _check_number(obj: object, name: str, lo: float, strict: bool, hi: float = _MAX_WEIGHT) -> None:
    """A finite number in (lo or [lo, hi]; a numpy scalar is stored as a Python float."""
    v = getattr(obj, name)
    ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) and \
        math.isfinite(v) and (v > lo if strict else v >= lo) and v <= hi
    if not ok:
        raise ValueError(f"{name}={v!r} is invalid: must be a finite number {'>' if strict else '>='} {lo} "
                         f"and <= {hi:g}")
    object.__setattr__(obj, name, float(v))


def _check_int(obj: object, name: str, lo: int, hi: int = _MAX_COUNT) -> None:
    """A whole number in [lo, hi]; a numpy integer is stored as a Python int."""
    v = getattr(obj, name)
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
        raise ValueError(f"{name}={v!r} is invalid: must be an integer in [{lo}, {hi}]")
    object.__setattr__(obj, name, int(v))


@dataclass(frozen=True, kw_only=True)
class MPCConfig:
    """Settings of :class:`MPCController` (all ours). The weights and horizon are the previous
    MPC's (:class:`CasadiMPCConfig`, chosen on seeds 100-109 of S4 and S2). Tried on training
    seeds 500-519 of Hard (w_pos 10 / 30 / 100, w_vel 0.3 / 1, horizon 3 / 4 s, 30 / 100 ADMM
    iterations) and of Medium and Easy (w_pos 30 / 100, observer time constant 0.5 / 1 s): the
    steady-state IQM moved by at most 0.6 %, so the defaults were kept (the error on the tiers
    is the estimate's, not the tracking's); the thruster model is what matters (Medium without
    it: 0.78 m instead of 0.10 m)."""

    horizon_s: float = 3.0  #: prediction horizon [s]
    intervals: int = 20  #: command blocks over the horizon (each a whole number of control steps)
    w_pos: float = 30.0  #: weight on the position error [1/m^2]
    w_psi: float = 1.0  #: weight on the heading error [1/rad^2]
    w_vel: float = 0.3  #: weight on the inertial velocity error to the reference's [s^2/m^2]
    w_r: float = 0.1  #: weight on the yaw-rate error [s^2/rad^2]
    w_force: float = 1e-3  #: weight on the normalised command (command / limit) [-]
    w_rate: float = 1e-2  #: weight on the change of the normalised command between blocks [-]
    w_terminal: float = 5.0  #: multiplier of the state weights at the last block's end [-]
    actuator_model: bool = True  #: the thruster lag and rate limit of the task spec in the model
    admm_iterations: int = 30  #: ADMM iterations per control step (fixed)
    admm_rho: float = 0.1  #: ADMM penalty, relative to the mean diagonal of each env's QP Hessian [-]
    disturbance_observer: bool = True  #: add the disturbance observer's estimate to the model
    dob_time_constant: float = 0.5  #: its low-pass time constant [s]

    def __post_init__(self) -> None:
        _check_number(self, "horizon_s", 0.0, True, _MAX_SECONDS)
        for n in ("w_pos", "w_psi", "w_vel", "w_r", "w_force", "w_rate"):
            _check_number(self, n, 0.0, False)
        for n in ("w_terminal", "admm_rho"):
            _check_number(self, n, 0.0, True)
        _check_number(self, "dob_time_constant", 0.0, True, _MAX_SECONDS)
        _check_int(self, "intervals", 1, 1000)
        _check_int(self, "admm_iterations", 1)
        for n in ("actuator_model", "disturbance_observer"):
            if not isinstance(getattr(self, n), (bool, np.bool_)):
                raise ValueError(f"{n}={getattr(self, n)!r} is invalid: must be True or False")
            object.__setattr__(self, n, bool(getattr(self, n)))
        if self.w_force + self.w_rate <= 0:
            raise ValueError(f"w_force={self.w_force!r} and w_rate={self.w_rate!r} are invalid: at least one "
                             f"must be > 0 (the QP needs a regularised command)")


def thruster_coefficients(spec: TaskSpec) -> tuple[float, float]:
    """(alpha, max change per step) of the spec's thrusters, normalised by the force limits,
    as the plant applies them (``auv_follow_env.sim``): ``alpha = 1 - exp(-dt / T)`` (1: no
    lag), ``rate * dt`` (inf: no rate limit)."""
    tc, rate = float(spec.thruster_tc_s), float(spec.thruster_rate)
    alpha = 1.0 - math.exp(-spec.dt / tc) if tc > 0 else 1.0
    return alpha, rate * spec.dt


# --- the linearisation: nominal rollout and its exact sensitivities (numba) ----------------

@njit(cache=True, inline="always")
def _rhs(s, F, cx, cy, d, lim, mi, out):
    """Continuous model eqs. (3)-(9): out = ds/dt for state s (6) and normalised force F (3).
    mi = (m, I_z, X_u, Y_v, N_r)."""
    ps, u, v, r = s[2], s[3], s[4], s[5]
    c, sn = math.cos(ps), math.sin(ps)
    ur = u - (c * cx + sn * cy)
    vr = v - (-sn * cx + c * cy)
    out[0] = c * u - sn * v
    out[1] = sn * u + c * v
    out[2] = r
    out[3] = (F[0] * lim[0] - mi[2] * ur + mi[0] * v * r + d[0]) / mi[0]
    out[4] = (F[1] * lim[1] - mi[3] * vr - mi[0] * u * r + d[1]) / mi[0]
    out[5] = (F[2] * lim[2] - mi[4] * r + d[2]) / mi[1]


@njit(cache=True, inline="always")
def _jac(s, cx, cy, mi, J):
    """J = d(rhs)/ds (6 x 6) at s (the force enters linearly: d(rhs)/dF is constant)."""
    ps, u, v, r = s[2], s[3], s[4], s[5]
    c, sn = math.cos(ps), math.sin(ps)
    m = mi[0]
    J[:, :] = 0.0
    J[0, 2] = -sn * u - c * v
    J[0, 3] = c
    J[0, 4] = -sn
    J[1, 2] = c * u - sn * v
    J[1, 3] = sn
    J[1, 4] = c
    J[2, 5] = 1.0
    J[3, 2] = -mi[2] / m * (sn * cx - c * cy)
    J[3, 3] = -mi[2] / m
    J[3, 4] = r
    J[3, 5] = v
    J[4, 2] = -mi[3] / m * (c * cx + sn * cy)
    J[4, 3] = -r
    J[4, 4] = -mi[3] / m
    J[4, 5] = -u
    J[5, 5] = -mi[4] / mi[1]


@njit(cache=True)
def _linearize(x0, F0, cur, dh, cbar, ref, gam, a0, msteps, dt, lim, mi, wsq, wterm, res, jac):
    """Nominal rollout of every env along its commands ``cbar`` and the Gauss-Newton data of
    the tracking cost.

    Args (n envs, Nb blocks, K = Nb msteps steps):
        x0 (n, 6): present state (x, y, psi, u, v, r); F0 (n, 3): applied force of the last step
        (normalised); cur (n, 2): inertial current; dh (n, 3): disturbance estimate [N, N, N m];
        cbar (n, Nb, 3): commands; ref (n, Nb, 6): reference (x, y, psi, vx, vy, r) at the blocks'
        ends; gam (K, Nb), a0 (K,): applied force at step j = a0[j] F0 + sum_b gam[j, b] c_b;
        wsq (6,): square roots of the state weights; wterm: sqrt of the terminal multiplier.
    Outputs:
        res (n, 6 Nb): weighted residuals; jac (n, 6 Nb, 3 Nb): their derivatives w.r.t. the
        commands (index 3 b + axis).
    """
    n = x0.shape[0]
    Nb = cbar.shape[1]
    K = gam.shape[0]
    h = dt
    s = np.empty(6)
    tmp = np.empty(6)
    k1 = np.empty(6)
    k2 = np.empty(6)
    k3 = np.empty(6)
    k4 = np.empty(6)
    F = np.empty(3)
    J1 = np.empty((6, 6))
    J2 = np.empty((6, 6))
    J3 = np.empty((6, 6))
    J4 = np.empty((6, 6))
    D1 = np.empty((6, 6))
    D2 = np.empty((6, 6))
    D3 = np.empty((6, 6))
    D4 = np.empty((6, 6))
    A = np.empty((6, 6))
    E1 = np.empty((6, 3))
    E2 = np.empty((6, 3))
    E3 = np.empty((6, 3))
    E4 = np.empty((6, 3))
    B = np.empty((6, 3))
    Bf = np.zeros((6, 3))
    Bf[3, 0] = lim[0] / mi[0]
    Bf[4, 1] = lim[1] / mi[0]
    Bf[5, 2] = lim[2] / mi[1]
    nv = 3 * Nb
    S = np.empty((6, nv))
    S2 = np.empty((6, nv))
    for i in range(n):
        cx, cy = cur[i, 0], cur[i, 1]
        d = dh[i]
        for c in range(6):
            s[c] = x0[i, c]
        S[:, :] = 0.0
        for j in range(K):
            bj = j // msteps
            for ax in range(3):
                f = a0[j] * F0[i, ax]
                for b in range(bj + 1):
                    f += gam[j, b] * cbar[i, b, ax]
                F[ax] = f
            # RK4 with its Jacobians: D = d k / d s, E = d k / d F
            _rhs(s, F, cx, cy, d, lim, mi, k1)
            _jac(s, cx, cy, mi, J1)
            for c in range(6):
                tmp[c] = s[c] + 0.5 * h * k1[c]
            _rhs(tmp, F, cx, cy, d, lim, mi, k2)
            _jac(tmp, cx, cy, mi, J2)
            for c in range(6):
                tmp[c] = s[c] + 0.5 * h * k2[c]
            _rhs(tmp, F, cx, cy, d, lim, mi, k3)
            _jac(tmp, cx, cy, mi, J3)
            for c in range(6):
                tmp[c] = s[c] + h * k3[c]
            _rhs(tmp, F, cx, cy, d, lim, mi, k4)
            _jac(tmp, cx, cy, mi, J4)
            for r_ in range(6):
                for c in range(6):
                    D1[r_, c] = J1[r_, c]
                for c in range(3):
                    E1[r_, c] = Bf[r_, c]
            for r_ in range(6):  # D2 = J2 (I + h/2 D1), E2 = J2 (h/2 E1) + Bf
                for c in range(6):
                    acc = J2[r_, c]
                    for q in range(6):
                        acc += 0.5 * h * J2[r_, q] * D1[q, c]
                    D2[r_, c] = acc
                for c in range(3):
                    acc = Bf[r_, c]
                    for q in range(6):
                        acc += 0.5 * h * J2[r_, q] * E1[q, c]
                    E2[r_, c] = acc
            for r_ in range(6):
                for c in range(6):
                    acc = J3[r_, c]
                    for q in range(6):
                        acc += 0.5 * h * J3[r_, q] * D2[q, c]
                    D3[r_, c] = acc
                for c in range(3):
                    acc = Bf[r_, c]
                    for q in range(6):
                        acc += 0.5 * h * J3[r_, q] * E2[q, c]
                    E3[r_, c] = acc
            for r_ in range(6):
                for c in range(6):
                    acc = J4[r_, c]
                    for q in range(6):
                        acc += h * J4[r_, q] * D3[q, c]
                    D4[r_, c] = acc
                for c in range(3):
                    acc = Bf[r_, c]
                    for q in range(6):
                        acc += h * J4[r_, q] * E3[q, c]
                    E4[r_, c] = acc
            for r_ in range(6):
                for c in range(6):
                    A[r_, c] = h / 6.0 * (D1[r_, c] + 2.0 * D2[r_, c] + 2.0 * D3[r_, c] + D4[r_, c])
                A[r_, r_] += 1.0
                for c in range(3):
                    B[r_, c] = h / 6.0 * (E1[r_, c] + 2.0 * E2[r_, c] + 2.0 * E3[r_, c] + E4[r_, c])
            for c in range(6):
                s[c] += h / 6.0 * (k1[c] + 2.0 * k2[c] + 2.0 * k3[c] + k4[c])
            # S <- A S + B dF/dc (only blocks 0..bj are nonzero)
            ncol = 3 * (bj + 1)
            for r_ in range(6):
                for c in range(ncol):
                    acc = 0.0
                    for q in range(6):
                        acc += A[r_, q] * S[q, c]
                    S2[r_, c] = acc
                for b in range(bj + 1):
                    g = gam[j, b]
                    for ax in range(3):
                        S2[r_, 3 * b + ax] += B[r_, ax] * g
            for r_ in range(6):
                for c in range(ncol):
                    S[r_, c] = S2[r_, c]
            if (j + 1) % msteps == 0:  # end of block bj: residuals and their rows
                row = 6 * bj
                wt = wterm if bj == Nb - 1 else 1.0
                cp, sp = math.cos(s[2]), math.sin(s[2])
                res[i, row] = wt * wsq[0] * (s[0] - ref[i, bj, 0])
                res[i, row + 1] = wt * wsq[1] * (s[1] - ref[i, bj, 1])
                res[i, row + 2] = wt * wsq[2] * (s[2] - ref[i, bj, 2])
                res[i, row + 3] = wt * wsq[3] * (cp * s[3] - sp * s[4] - ref[i, bj, 3])
                res[i, row + 4] = wt * wsq[4] * (sp * s[3] + cp * s[4] - ref[i, bj, 4])
                res[i, row + 5] = wt * wsq[5] * (s[5] - ref[i, bj, 5])
                dvx2 = -sp * s[3] - cp * s[4]
                dvy2 = cp * s[3] - sp * s[4]
                for c in range(nv):
                    if c < ncol:
                        jac[i, row, c] = wt * wsq[0] * S[0, c]
                        jac[i, row + 1, c] = wt * wsq[1] * S[1, c]
                        jac[i, row + 2, c] = wt * wsq[2] * S[2, c]
                        jac[i, row + 3, c] = wt * wsq[3] * (dvx2 * S[2, c] + cp * S[3, c] - sp * S[4, c])
                        jac[i, row + 4, c] = wt * wsq[4] * (dvy2 * S[2, c] + sp * S[3, c] + cp * S[4, c])
                        jac[i, row + 5, c] = wt * wsq[5] * S[5, c]
                    else:
                        for q in range(6):
                            jac[i, row + q, c] = 0.0


@njit(cache=True)
def _factor(H, reg, Rb, rho, sigma, L):
    """L L' = H + reg + sigma I + A' diag(rho) A for every env (n, nv, nv) (symmetric positive
    definite); L lower. A = [I; R] as in :func:`_admm`; ``reg`` (nv, nv) is shared, ``rho``
    (n, nc) and ``sigma`` (n,) are per env."""
    n, nv, _ = H.shape
    Nb = nv // 3
    has_rate = Rb.shape[0] > 0
    for i in range(n):
        for a in range(nv):
            for c in range(a + 1):
                acc = H[i, a, c] + reg[a, c]
                if a == c:
                    acc += sigma[i] + rho[i, a]
                if has_rate and a % 3 == c % 3:  # R' diag(rho_R) R, per axis
                    ba, bc, ax = a // 3, c // 3, a % 3
                    for b in range(ba, Nb):
                        acc += Rb[b, ba] * rho[i, nv + 3 * b + ax] * Rb[b, bc]
                for k in range(c):
                    acc -= L[i, a, k] * L[i, c, k]
                if a == c:
                    L[i, a, a] = math.sqrt(acc)
                else:
                    L[i, a, c] = acc / L[i, c, c]
            for c in range(a + 1, nv):
                L[i, a, c] = 0.0


@njit(cache=True)
def _admm(L, q, Rb, lo, hi, x, z, y, rho, sigma, iters, relax):
    """OSQP's ADMM iteration for min 1/2 x'Hx + q'x s.t. lo <= A x <= hi, for every env, with
    A = [I; R] (R: the rate-limit rows, the same (Nb, Nb) matrix ``Rb`` for each axis, index
    3 b + axis; Rb of size 0: A = I) and L L' = H + sigma I + A' diag(rho) A (n, nv, nv) given
    (``rho``: (n, nc), a penalty per constraint; ``sigma``: (n,)).
    x (n, nv), z and y (n, nc) are the warm start and are updated in place."""
    n, nv = x.shape
    Nb = nv // 3
    has_rate = Rb.shape[0] > 0
    rhs = np.empty(nv)
    xt = np.empty(nv)
    w = np.empty(z.shape[1])
    for i in range(n):
        for _ in range(iters):
            for c in range(z.shape[1]):
                w[c] = rho[i, c] * z[i, c] - y[i, c]
            for a in range(nv):
                rhs[a] = sigma[i] * x[i, a] - q[i, a] + w[a]
            if has_rate:  # + R' w2
                for bb in range(Nb):
                    for b in range(bb, Nb):
                        rb = Rb[b, bb]
                        if rb != 0.0:
                            for ax in range(3):
                                rhs[3 * bb + ax] += rb * w[nv + 3 * b + ax]
            for a in range(nv):  # forward: L t = rhs
                acc = rhs[a]
                for k in range(a):
                    acc -= L[i, a, k] * xt[k]
                xt[a] = acc / L[i, a, a]
            for a in range(nv - 1, -1, -1):  # backward: L' xt = t
                acc = xt[a]
                for k in range(a + 1, nv):
                    acc -= L[i, k, a] * xt[k]
                xt[a] = acc / L[i, a, a]
            for c in range(z.shape[1]):
                if c < nv:
                    zt = xt[c]
                else:
                    b, ax = (c - nv) // 3, (c - nv) % 3
                    zt = 0.0
                    for bb in range(b + 1):
                        zt += Rb[b, bb] * xt[3 * bb + ax]
                zr = relax * zt + (1.0 - relax) * z[i, c]
                zn = zr + y[i, c] / rho[i, c]
                if zn < lo[i, c]:
                    zn = lo[i, c]
                elif zn > hi[i, c]:
                    zn = hi[i, c]
                y[i, c] += rho[i, c] * (zr - zn)
                z[i, c] = zn
            for a in range(nv):
                x[i, a] = relax * xt[a] + (1.0 - relax) * x[i, a]


def _reference_track(estimator: TargetEstimator, spec: TaskSpec, times: np.ndarray, h: float, valid: np.ndarray,
                     x0: np.ndarray) -> np.ndarray:
    """(N_env, len(times) - 2, 6): the reference point's pose (heading unwrapped near the
    follower's) and its velocity by central differences of spacing ``h`` at the inner samples of
    ``times`` (the filter's predicted target); envs without a fix hold their pose ``x0``."""
    px, py, ps = estimator.trajectory(times, frame="odometry")
    pdx, pdy = spec.p_d
    c, s = np.cos(ps), np.sin(ps)
    rx, ry = px + c * pdx - s * pdy, py + s * pdx + c * pdy
    rpsi = ps + spec.psi_d  # reference heading near the follower's unwrapped heading
    k = np.round((x0[:, 2] - rpsi[:, 1]) / (2 * math.pi))
    rpsi = rpsi + 2 * math.pi * k[:, None]
    vx, vy, vr = ((q[:, 2:] - q[:, :-2]) / (2 * h) for q in (rx, ry, rpsi))
    ref = np.stack([rx[:, 1:-1], ry[:, 1:-1], rpsi[:, 1:-1], vx, vy, vr], axis=-1)
    hold = ~valid
    if hold.any():
        ref[hold] = 0.0
        ref[hold, :, 0] = x0[hold, 0, None]
        ref[hold, :, 1] = x0[hold, 1, None]
        ref[hold, :, 2] = x0[hold, 2, None]
    return ref


def _own_reference(estimator: TargetEstimator, spec: TaskSpec, observation) -> np.ndarray:
    """The MPC's own reference point now (N, 3), relative to the follower; a peek at the filter."""
    obs = np.atleast_2d(observation)
    if obs.dtype not in (np.float64, np.float32):
        obs = np.asarray(obs, dtype=np.float64)
    # (a float32 batch is converted by the estimator: its copy is private, kept by the peek as is)
    est = estimator.step(obs, None, commit=False, with_cov=False)
    pdx, pdy = spec.p_d
    c, s = np.cos(est.rel_psi), np.sin(est.rel_psi)
    ref = np.stack([est.rel_x + c * pdx - s * pdy, est.rel_y + s * pdx + c * pdy, est.rel_psi + spec.psi_d], axis=-1)
    ref[~est.valid] = 0.0
    return ref


class MPCController(ScriptedPolicy):
    """Delay-aware MPC with the thrusters in its model (see the module docstring), batched:
    one linearisation and one ADMM solve for all N envs per control step.

    ``solve_times`` keeps, per call, the wall time of the MPC's own part (linearisation, QP,
    ADMM) divided by the number of envs [s per env-step]; ``last_solution`` the first command
    of each env's ADMM solution (N, 3), normalised, before the final clip;
    ``last_violation`` how far ADMM's whole solution was outside its constraints (N,)
    (normalised units); ``applied_force`` the force (N, 3) [N, N, N m] the model predicts the
    thrusters apply at this step (what the disturbance observer is told).

    Args:
        spec: the env's TaskSpec (its ``thruster_tc_s`` and ``thruster_rate`` enter the model).
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
        cfg = self.config = config if config is not None else MPCConfig()
        self.name = name
        steps = cfg.horizon_s / cfg.intervals / spec.dt
        if abs(steps - round(steps)) > 1e-9 * max(1.0, steps) or round(steps) < 1:
            raise ValueError(f"horizon_s={cfg.horizon_s!r} is invalid: horizon_s / intervals ({cfg.intervals}) must "
                             f"be a whole number >= 1 of control steps of dt={spec.dt} s")
        self.block_steps = m = int(round(steps))
        self.estimator = TargetEstimator(spec, estimator_config)
        self.dob = (DisturbanceObserver(spec.nominal, spec.dt, spec.force_limits, cfg.dob_time_constant)
                    if cfg.disturbance_observer else None)
        self.alpha, self.rate_step = thruster_coefficients(spec) if cfg.actuator_model else (1.0, math.inf)
        Nb = cfg.intervals
        K = Nb * m
        self._nv = nv = 3 * Nb
        a = self.alpha
        gam = np.zeros((K, Nb))
        a0 = np.zeros(K)
        prev_g, prev_a = np.zeros(Nb), 1.0
        for j in range(K):  # F_j = (1 - alpha) F_{j-1} + alpha c_{b(j)}
            gam[j] = (1.0 - a) * prev_g
            gam[j, j // m] += a
            a0[j] = (1.0 - a) * prev_a
            prev_g, prev_a = gam[j], a0[j]
        self._gam, self._a0 = gam, a0
        # constraints on c (index 3 b + axis): |c| <= 1, and (rate limit) c_b - F_b in +-rate/alpha
        rows = [np.eye(nv)]
        self._rate_f0 = np.zeros(0)
        if math.isfinite(self.rate_step):
            R = np.eye(nv)
            f0 = np.ones(Nb)  # coefficient of F0 in F_b (the applied force before block b)
            for b in range(1, Nb):
                j = b * m - 1
                f0[b] = a0[j]
                for bb in range(b):
                    R[3 * b:3 * b + 3, 3 * bb:3 * bb + 3] -= gam[j, bb] * np.eye(3)
            rows.append(R)
            self._rate_f0 = np.repeat(f0, 3)
            self._Rb = np.ascontiguousarray(R[0::3, 0::3])  # the same for each axis
        else:
            self._Rb = np.zeros((0, 0))
        self._A = np.ascontiguousarray(np.vstack(rows))
        Dm = np.eye(nv) - np.eye(nv, k=-3)  # command changes between blocks
        self._DtD = Dm.T @ Dm
        nm = spec.nominal
        self._mi = np.array([nm.m, nm.I_z, nm.X_u, nm.Y_v, nm.N_r], dtype=np.float64)
        self._wsq = np.sqrt(np.array([cfg.w_pos, cfg.w_pos, cfg.w_psi, cfg.w_vel, cfg.w_vel, cfg.w_r]))
        self._times = spec.dt * m * np.arange(0, Nb + 2)  # reference samples incl. one either side
        self._batch: int | None = None
        self.solve_times: list[float] = []
        self.last_solution: np.ndarray | None = None
        self.last_violation: np.ndarray | None = None
        self.applied_force: np.ndarray | None = None

    # ------------------------------------------------------------------------------------
    def _references(self, valid: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """(N_env, intervals, 6): reference point pose and velocity at the blocks' ends."""
        return _reference_track(self.estimator, self.spec, self._times, self._times[1], valid, x0)

    def reference(self, observation) -> np.ndarray:
        return _own_reference(self.estimator, self.spec, observation)

    def _fresh(self, n: int, psi_f: np.ndarray) -> None:
        nv, nc = self._nv, self._A.shape[0]
        self._batch = n
        self._c = np.zeros((n, nv))
        self._z = np.zeros((n, nc))
        self._y = np.zeros((n, nc))
        self._F = np.zeros((n, 3))  # applied force of the last step [N, N, N m] (the plant starts at 0)
        self._cmd = np.zeros((n, 3))  # last command (normalised)
        self._psi_unwrapped = psi_f.copy()

    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        o = decode(obs)
        n = obs.shape[0]
        est = self.estimator.step(obs, reset_mask, with_cov=False)
        odom, psi_f = self.estimator.follower_odometry()
        if self._batch != n:
            self._fresh(n, psi_f)
            reset_mask = np.ones(n, dtype=bool)
        r = np.asarray(reset_mask, dtype=bool)
        if r.any():
            for arr in (self._c, self._z, self._y, self._F, self._cmd):
                arr[r] = 0.0
        dpsi = psi_f - self._psi_unwrapped
        self._psi_unwrapped = np.where(r, psi_f, self._psi_unwrapped + np.arctan2(np.sin(dpsi), np.cos(dpsi)))
        x0 = np.column_stack([odom, self._psi_unwrapped, o["u"], o["v"], o["r"]])
        cur = np.column_stack([np.cos(psi_f) * o["current_u"] - np.sin(psi_f) * o["current_v"],
                               np.sin(psi_f) * o["current_u"] + np.cos(psi_f) * o["current_v"]])
        if self.dob is not None:
            nu = np.column_stack([o["u"], o["v"], o["r"]])
            d_hat = self.dob.update(nu, np.column_stack([o["current_u"], o["current_v"]]), r)
        else:
            d_hat = np.zeros((n, 3))
        refs = self._references(est.valid, x0)
        t0 = time.perf_counter()
        F0 = self._F / self._limits
        cmd = self._solve(x0, F0, cur, d_hat, refs, r)
        self.solve_times.append((time.perf_counter() - t0) / n)
        # the exact feasible interval of this step's command: |c| <= 1, |alpha (c - F0)| <= rate dt
        lo, hi = np.full((n, 3), -1.0), np.full((n, 3), 1.0)
        if math.isfinite(self.rate_step):
            band = self.rate_step / self.alpha - 1e-6  # margin: the plant's float32 action stays inside
            lo, hi = np.maximum(lo, F0 - band), np.minimum(hi, F0 + band)
        cmd = np.clip(cmd, lo, hi).astype(np.float32).astype(np.float64)  # what the plant will apply
        self._cmd = cmd
        Fc = cmd * self._limits
        self._F = self._F + self.alpha * (Fc - self._F) if self.alpha < 1.0 else Fc  # the plant's lag
        self.applied_force = self._F.copy()
        if self.dob is not None:
            self.dob.applied(self._F)
        return Fc

    def _solve(self, x0, F0, cur, d_hat, refs, cold) -> np.ndarray:
        """One Gauss-Newton step + ADMM for every env (``cold``: envs whose episode starts here);
        returns the first commands (n, 3)."""
        cfg = self.config
        n, Nb, nv = x0.shape[0], cfg.intervals, self._nv
        cbar = np.clip(self._c, -1.0, 1.0)
        res = np.empty((n, 6 * Nb))
        jac = np.empty((n, 6 * Nb, nv))
        _linearize(x0, F0, cur, d_hat, cbar.reshape(n, Nb, 3), refs, self._gam, self._a0, self.block_steps,
                   self.spec.dt, self._limits, self._mi, self._wsq, math.sqrt(cfg.w_terminal), res, jac)
        Jt = jac.transpose(0, 2, 1)
        H = Jt @ jac  # Gauss-Newton: the QP in c of |res + jac (c - cbar)|^2 / 2 + regularisation
        q = (Jt @ (res - (jac @ cbar[..., None])[..., 0])[..., None])[..., 0]
        q[:, :3] -= cfg.w_rate * self._cmd  # the first block's change is against the last command
        reg = cfg.w_force * np.eye(nv) + cfg.w_rate * self._DtD
        diag = np.diagonal(H, axis1=1, axis2=2) + np.diagonal(reg)  # (n, nv)
        # ADMM penalty: admm_rho times the mean diagonal of the env's Hessian, the same for every
        # constraint (a penalty scaled per variable, or adapted from step to step by OSQP's
        # residual-balance rule, left more steps outside the constraints on Hard); per env, so
        # an env's solution does not depend on the others in the batch
        nc = self._A.shape[0]
        rho = np.repeat((cfg.admm_rho * diag.mean(axis=1))[:, None], nc, axis=1)
        sigma = 1e-6 * diag.mean(axis=1)
        L = np.empty_like(H)
        _factor(H, reg, self._Rb, rho, sigma, L)
        lo = np.full((n, self._A.shape[0]), -1.0)
        hi = np.full((n, self._A.shape[0]), 1.0)
        if self._rate_f0.size:
            band = self.rate_step / self.alpha
            base = self._rate_f0[None, :] * np.tile(F0, (1, Nb))  # F0's share of F_b, index 3 b + axis
            lo[:, nv:] = base - band
            hi[:, nv:] = base + band
        _admm(L, q, self._Rb, lo, hi, self._c, self._z, self._y, rho, sigma, cfg.admm_iterations, 1.6)
        # products per env (a (1, k) row each), so that an env's numbers do not depend on the batch
        Ax = (self._c[:, None, :] @ self._A.T)[:, 0]
        viol = np.max(np.maximum(np.maximum(lo - Ax, Ax - hi), 0.0), axis=1)
        # a fresh episode (no warm start) or a solution still outside its constraints by more
        # than 1e-3 (a packet moved the reference): ten times the iterations, for those envs only
        again = np.flatnonzero(cold | (viol > 1e-3))
        if again.size:
            c, z, y = self._c[again], self._z[again], self._y[again]
            _admm(L[again], q[again], self._Rb, lo[again], hi[again], c, z, y, rho[again], sigma[again],
                  10 * cfg.admm_iterations, 1.6)
            self._c[again], self._z[again], self._y[again] = c, z, y
        Ax = (self._c[:, None, :] @ self._A.T)[:, 0]
        self.last_violation = np.max(np.maximum(np.maximum(lo - Ax, Ax - hi), 0.0), axis=1)
        self.last_solution = self._c[:, :3].copy()
        return self._c[:, :3].copy()


# --- the previous MPC (CasADi, one problem per env, no actuator model) ------------------------

NX, NU = 6, 3


@dataclass(frozen=True, kw_only=True)
class CasadiMPCConfig:
    """Settings of :class:`CasadiMPCController` (all ours). w_pos and w_vel were picked among
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
        if self.qp_solver not in ("osqp", "qrqp"):
            raise ValueError(f"qp_solver={self.qp_solver!r} is invalid: must be 'osqp' or 'qrqp'")
        _check_number(self, "horizon_s", 0.0, True, _MAX_SECONDS)
        for n in ("w_pos", "w_psi", "w_vel", "w_r", "w_force", "w_rate"):
            _check_number(self, n, 0.0, False)
        _check_number(self, "w_terminal", 0.0, True)
        _check_number(self, "dob_time_constant", 0.0, True, _MAX_SECONDS)
        _check_int(self, "intervals", 1, 1000)
        _check_int(self, "sqp_iterations", 1, 100)
        if not isinstance(self.disturbance_observer, (bool, np.bool_)):
            raise ValueError(f"disturbance_observer={self.disturbance_observer!r} is invalid: must be True or False")
        object.__setattr__(self, "disturbance_observer", bool(self.disturbance_observer))
        if self.w_force + self.w_rate <= 0:
            raise ValueError(f"w_force={self.w_force!r} and w_rate={self.w_rate!r} are invalid: at least one "
                             f"must be > 0 (the QP needs a regularised force)")


def _build(spec: TaskSpec, cfg: CasadiMPCConfig):
    import casadi as ca  # only when a CasadiMPCController is made

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


class CasadiMPCController(ScriptedPolicy):
    """The previous ``MPC`` (no actuator in its model; see the module docstring), batched over N envs (one
    warm-started problem per env; ``solve_times`` keeps the wall time of each env-step's solve).

    Args:
        spec: the env's TaskSpec.
        config: :class:`CasadiMPCConfig`.
        estimator_config: the target estimator's settings (default: as ``PROPOSED_KF``).
        name: label used in tables.
    """

    name = "MPC_CASADI"

    def __init__(self, spec: TaskSpec, config: CasadiMPCConfig | None = None,
                 estimator_config: EstimatorConfig | None = None, name: str = "MPC_CASADI") -> None:
        super().__init__(spec)
        if config is not None and not isinstance(config, CasadiMPCConfig):
            raise ValueError(f"config={config!r} is invalid: must be a CasadiMPCConfig or None")
        self.config = config if config is not None else CasadiMPCConfig()
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
        return _reference_track(self.estimator, self.spec, self._times, self._h, valid, x0)

    def reference(self, observation) -> np.ndarray:
        return _own_reference(self.estimator, self.spec, observation)

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
