"""The paper's hierarchical law, written once: predictor (13)-(17), reference (21),
outer loop (25)-(30) and inner robust loop (31)-(35).

PROPOSED, ROBUST_ONLY and PRED_ONLY are this one law with Table 1's switches.

On v1 observations (the acoustic-link layout, 20 fields) the predictor extrapolates over
each packet's observed ``packet_age`` instead of the nominal tau, and until the first packet
has arrived (``has_packet`` = 0) the law holds position: reference = the follower's own pose,
zero desired velocity. On v0 observations nothing of this applies (bit-identical to before).

Everything is computed in the follower's body frame with the follower at the origin and
heading 0: the laws are equivariant under rotations and translations (K_p is a scalar
gain), so this equals the paper's inertial-frame computation followed by R(psi)^T, eq. (27).

Speed: :class:`HierarchicalController` (without estimator or disturbance observer) runs the
law as two compiled passes over the batch (:func:`_reference_all`, :func:`_law_pass`), each
libm function (atan2, cos, sin: glibc's, as numpy's float64 ufuncs call them) evaluated once
per env, instead of the numpy composition of the functions below; the arithmetic is the
same IEEE operations in the same order, so the results are bit-identical (tested against
the composition; numba contracts nothing to FMA without fastmath). Batches of
:data:`THREADED_MIN_ENVS` envs or more run the passes on numba's threads (envs are
independent: the same bits). :meth:`reference` keeps
its result for the observation it was given, and the next :meth:`forces` on a bit-identical
observation reuses it (evaluation calls ``reference`` on the observation the next
``predict`` sees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from auv_follow_env.dynamics import recompiled
from auv_follow_env.layout import LAYOUTS, OBS_DIM_V1, OBS_INDEX, OBS_INDEX_V1, decode
from auv_follow_env.params import TaskSpec
from controllers.base import FilteredDerivative, ScriptedPolicy, check_real, sat, wrap_to_pi
from controllers.disturbance import DisturbanceObserver
from controllers.estimator import TargetEstimator

__all__ = ["Gains", "HierarchicalController", "predict_target", "reference_point", "outer_loop",
           "inner_loop", "prediction_horizon", "no_packet_mask", "zero_where"]


@dataclass(frozen=True, kw_only=True)
class Gains:
    """Gains of the hierarchical law: one set for the whole study (docs/paper_notes.md suggested values;
    the paper gives none). Shared by PROPOSED, ROBUST_ONLY and PRED_ONLY."""

    K_p: float = 1.0  #: outer-loop position gain, eq. (25) [1/s]
    K_psi: float = 1.0  #: heading gain, eq. (29) [1/s]
    K_u: float = 50.0  #: surge velocity gain, eq. (32) [N s/m]
    K_v: float = 50.0  #: sway velocity gain, eq. (33) [N s/m]
    K_r: float = 4.0  #: yaw-rate gain, eq. (34) [N m s]
    rho: tuple[float, float, float] = (4.0, 4.0, 0.3)  #: robust gains [N, N, N m]
    phi: tuple[float, float, float] = (0.04, 0.04, 0.04)  #: boundary layers [m/s, m/s, rad/s]
    derivative_tc: float = 0.05  #: filter time constant for u_d, v_d, r_d derivatives [s]

    def __post_init__(self) -> None:
        for n in ("K_p", "K_psi", "K_u", "K_v", "K_r"):
            check_real(n, getattr(self, n), 0.0, True)
        check_real("derivative_tc", self.derivative_tc, 0.0, False)
        for name, strict, what in (("rho", False, ">= 0"), ("phi", True, "> 0")):
            v = getattr(self, name)
            try:
                if not isinstance(v, (tuple, list, np.ndarray)) or len(v) != 3:
                    raise ValueError
                for x in v:
                    check_real(name, x, 0.0, strict)
            except ValueError:
                raise ValueError(f"{name}={v!r} is invalid: must be three finite numbers {what}") from None


def _rot(psi: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(psi), np.sin(psi)
    return c * x - s * y, s * x + c * y


def prediction_horizon(o: dict[str, np.ndarray], tau: float):
    """How old the target fields are [s]: ``packet_age`` on a v1 observation, else tau (v0)."""
    return o["packet_age"] if "packet_age" in o else tau


def no_packet_mask(o: dict[str, np.ndarray]) -> np.ndarray | None:
    """Envs with no packet yet (v1, ``has_packet`` = 0), or None on a v0 observation."""
    return o["has_packet"] < 0.5 if "has_packet" in o else None


def zero_where(values, mask: np.ndarray | None):
    """Zero every array of ``values`` where ``mask`` is set (hold position without a packet)."""
    if mask is None or not mask.any():
        return values
    return tuple(np.where(mask, 0.0, v) for v in values)


def predict_target(o: dict[str, np.ndarray], tau, enabled: bool = True):
    """Eqs. (13)-(17): first-order extrapolation of the delayed target over tau.

    Args:
        o: decoded observation (body frame).
        tau: delay [s]: a number, or an array (N,) of per-env ages (v1 ``packet_age``).
        enabled: False gives eta_hat = eta_t(t - tau) (ROBUST_ONLY, Table 1).

    Returns:
        (x_hat, y_hat, psi_hat, u_hat, v_hat, r_hat), positions/heading relative to the follower.
    """
    psi_d = np.arctan2(o["target_sin_dpsi"], o["target_cos_dpsi"])
    u, v, r = o["target_u"], o["target_v"], o["target_r"]  # eq. (13)
    x, y = o["target_dx"], o["target_dy"]
    if enabled:
        vx, vy = _rot(psi_d, u, v)  # eq. (17)
        x, y, psi_d = x + vx * tau, y + vy * tau, psi_d + r * tau  # eqs. (14)-(16)
    return x, y, psi_d, u, v, r


def reference_point(x_hat, y_hat, psi_hat, p_d: tuple[float, float], psi_d: float):
    """Eq. (21): p_ref = p_hat + R(psi_hat) p_d, psi_ref = psi_hat + psi_d."""
    ox, oy = _rot(psi_hat, p_d[0], p_d[1])
    return x_hat + ox, y_hat + oy, psi_hat + psi_d


def outer_loop(ref, pred, p_d: tuple[float, float], gains: Gains):
    """Eqs. (22)-(30) in the follower frame: returns (u_d, v_d, r_d)."""
    x_ref, y_ref, psi_ref = ref
    _, _, psi_hat, u_hat, v_hat, r_hat = pred
    e_x, e_y = -x_ref, -y_ref  # eq. (22): e_p = p - p_ref with p = 0
    e_psi = wrap_to_pi(-psi_ref)  # eq. (24)
    fx, fy = _rot(psi_hat, u_hat, v_hat)
    ox, oy = _rot(psi_hat, p_d[0], p_d[1])
    vffx = fx - r_hat * oy  # eq. (26): J = [[0, -1], [1, 0]]
    vffy = fy + r_hat * ox
    u_d = -gains.K_p * e_x + vffx  # eqs. (25), (27)-(28)
    v_d = -gains.K_p * e_y + vffy
    r_d = -gains.K_psi * e_psi + r_hat  # eq. (29)
    return u_d, v_d, r_d


def inner_loop(o: dict[str, np.ndarray], desired, desired_dot, nominal, gains: Gains, robust: bool):
    """Eqs. (31)-(35): (F_u, F_v, F_r) [N, N, N m]. ``robust=False`` sets rho = 0 (PRED_ONLY)."""
    u, v, r = o["u"], o["v"], o["r"]
    u_d, v_d, r_d = desired
    ud_dot, vd_dot, rd_dot = desired_dot
    e_u, e_v, e_r = u - u_d, v - v_d, r - r_d  # eq. (31)
    u_r = u - o["current_u"]  # eq. (9), with the measured current
    v_r = v - o["current_v"]
    m, I_z = nominal.m, nominal.I_z
    rho = gains.rho if robust else (0.0, 0.0, 0.0)
    phi = gains.phi
    F_u = m * ud_dot + nominal.X_u * u_r - m * v * r - gains.K_u * e_u - rho[0] * sat(e_u / phi[0])  # (32)
    F_v = m * vd_dot + nominal.Y_v * v_r + m * u * r - gains.K_v * e_v - rho[1] * sat(e_v / phi[1])  # (33)
    F_r = I_z * rd_dot + nominal.N_r * r - gains.K_r * e_r - rho[2] * sat(e_r / phi[2])  # (34)
    return F_u, F_v, F_r


# --- the compiled passes of HierarchicalController (same operations as the functions above) --
_U, _V, _R = OBS_INDEX["u"], OBS_INDEX["v"], OBS_INDEX["r"]
_DX, _DY = OBS_INDEX["target_dx"], OBS_INDEX["target_dy"]
_COS, _SIN = OBS_INDEX["target_cos_dpsi"], OBS_INDEX["target_sin_dpsi"]
_TU, _TV, _TR = OBS_INDEX["target_u"], OBS_INDEX["target_v"], OBS_INDEX["target_r"]
_CU, _CV = OBS_INDEX["current_u"], OBS_INDEX["current_v"]
_AGE, _HAS = OBS_INDEX_V1["packet_age"], OBS_INDEX_V1["has_packet"]


def _reference_all(a, enabled, tau, tau_col, pdx, pdy, psi_off, hold_col, ref, neg, c, s):
    """:func:`predict_target` then :func:`reference_point`, env by env: psi_d = atan2 of the
    packet's heading cos/sin, the prediction (tau = ``a[:, tau_col]`` if tau_col >= 0, the v1
    packet age, else ``tau``), the reference into ref (N, 3), zero where ``a[:, hold_col] < 0.5``
    if hold_col >= 0 (:func:`no_packet_mask`); neg = -ref[:, 2]; c, s = cos, sin of the
    predicted heading psi_hat."""
    for i in prange(a.shape[0]):
        psi_d = math.atan2(a[i, _SIN], a[i, _COS])
        if enabled:
            cd = math.cos(psi_d)
            sd = math.sin(psi_d)
            t = a[i, tau_col] if tau_col >= 0 else tau
            u = a[i, _TU]
            v = a[i, _TV]
            vx = cd * u - sd * v
            vy = sd * u + cd * v
            x = a[i, _DX] + vx * t
            y = a[i, _DY] + vy * t
            psi = psi_d + a[i, _TR] * t
        else:
            x = a[i, _DX]
            y = a[i, _DY]
            psi = psi_d
        ci = math.cos(psi)
        si = math.sin(psi)
        c[i] = ci
        s[i] = si
        ox = ci * pdx - si * pdy
        oy = si * pdx + ci * pdy
        xr = x + ox
        yr = y + oy
        pr = psi + psi_off
        if hold_col >= 0 and a[i, hold_col] < 0.5:
            xr = 0.0
            yr = 0.0
            pr = 0.0
        ref[i, 0] = xr
        ref[i, 1] = yr
        ref[i, 2] = pr
        neg[i] = -pr


@njit(cache=True, inline="always")
def _sat(z):
    """np.clip(z, -1, 1) (NaN stays NaN)."""
    if z < -1.0:
        return -1.0
    if z > 1.0:
        return 1.0
    return z


@njit(cache=True, inline="always")
def _law_env(i, a, e_x, e_y, ci, si, negi, u_hat, v_hat, r_hat, held, pdx, pdy, gain, model, fa, fb, prev, d,
             restart, F):
    """:func:`outer_loop` (ci, si = cos, sin of psi_hat; negi = -psi_ref), zeroed if ``held``, the
    filtered derivative (restarted if ``restart``) and :func:`inner_loop` for env i into F[i]."""
    nkp, nkpsi, k_u, k_v, k_r = gain[0], gain[1], gain[2], gain[3], gain[4]
    rho0, rho1, rho2, phi0, phi1, phi2 = gain[5], gain[6], gain[7], gain[8], gain[9], gain[10]
    m, i_z, x_u, y_v, n_r = model[0], model[1], model[2], model[3], model[4]
    e_psi = math.atan2(math.sin(negi), math.cos(negi))
    fx = ci * u_hat - si * v_hat
    fy = si * u_hat + ci * v_hat
    ox = ci * pdx - si * pdy
    oy = si * pdx + ci * pdy
    vffx = fx - r_hat * oy
    vffy = fy + r_hat * ox
    u_d = nkp * e_x + vffx
    v_d = nkp * e_y + vffy
    r_d = nkpsi * e_psi + r_hat
    if held:
        u_d = 0.0
        v_d = 0.0
        r_d = 0.0
    if restart:
        prev[i, 0] = u_d
        prev[i, 1] = v_d
        prev[i, 2] = r_d
        d[i, 0] = 0.0
        d[i, 1] = 0.0
        d[i, 2] = 0.0
    ud_dot = fa * (u_d - prev[i, 0]) + fb * d[i, 0]
    vd_dot = fa * (v_d - prev[i, 1]) + fb * d[i, 1]
    rd_dot = fa * (r_d - prev[i, 2]) + fb * d[i, 2]
    d[i, 0] = ud_dot
    d[i, 1] = vd_dot
    d[i, 2] = rd_dot
    prev[i, 0] = u_d
    prev[i, 1] = v_d
    prev[i, 2] = r_d
    u = a[i, _U]
    v = a[i, _V]
    r = a[i, _R]
    e_u = u - u_d
    e_v = v - v_d
    e_r = r - r_d
    u_r = u - a[i, _CU]
    v_r = v - a[i, _CV]
    F[i, 0] = m * ud_dot + x_u * u_r - m * v * r - k_u * e_u - rho0 * _sat(e_u / phi0)
    F[i, 1] = m * vd_dot + y_v * v_r + m * u * r - k_v * e_v - rho1 * _sat(e_v / phi1)
    F[i, 2] = i_z * rd_dot + n_r * r - k_r * e_r - rho2 * _sat(e_r / phi2)


def _law_pass(a, ref, c, s, neg, hold_col, pdx, pdy, gain, model, fa, fb, prev, d, reset, reset_all, F):
    """:func:`outer_loop` (``c``, ``s`` = cos, sin of psi_hat; neg = -psi_ref, wrapped to
    (-pi, pi] here as ``wrap_to_pi`` does, eq. (24)),
    zeroed where held, the filtered derivative (state prev, d; restarted where ``reset`` or
    everywhere if ``reset_all``) and :func:`inner_loop` into F (N, 3).

    gain = (-K_p, -K_psi, K_u, K_v, K_r, rho_u, rho_v, rho_r, phi_u, phi_v, phi_r),
    model = (m, I_z, X_u, Y_v, N_r)."""
    for i in prange(a.shape[0]):
        held = hold_col >= 0 and a[i, hold_col] < 0.5
        _law_env(i, a, -ref[i, 0], -ref[i, 1], c[i], s[i], neg[i], a[i, _TU], a[i, _TV], a[i, _TR], held, pdx, pdy,
                 gain, model, fa, fb, prev, d, reset_all or reset[i], F)


@njit(cache=True, inline="always")
def _estimate_reference(i, ex, ey, epsi, valid, pdx, pdy, psi_off):
    """:func:`reference_point` of a target estimate's env i (relative pose ex, ey, epsi), zero
    where not ``valid`` (hold position): (x_ref, y_ref, psi_ref, cos psi_hat, sin psi_hat)."""
    ci = math.cos(epsi[i])
    si = math.sin(epsi[i])
    ox = ci * pdx - si * pdy
    oy = si * pdx + ci * pdy
    if not valid[i]:
        return 0.0, 0.0, 0.0, ci, si
    return ex[i] + ox, ey[i] + oy, epsi[i] + psi_off, ci, si


def _estimate_reference_all(ex, ey, epsi, valid, pdx, pdy, psi_off, ref):
    """:func:`_estimate_reference` of every env into ref (N, 3)."""
    for i in prange(ex.shape[0]):
        xr, yr, pr, _, _ = _estimate_reference(i, ex, ey, epsi, valid, pdx, pdy, psi_off)
        ref[i, 0] = xr
        ref[i, 1] = yr
        ref[i, 2] = pr


def _estimate_law_pass(a, ex, ey, epsi, eu, ev, er, valid, pdx, pdy, psi_off, gain, model, fa, fb, prev, d, reset,
                       reset_all, F):
    """The law on a target estimate (relative pose ex, ey, epsi and body velocity eu, ev, er;
    hold position where not ``valid``): :func:`reference_point`, then as :func:`_law_pass`."""
    for i in prange(a.shape[0]):
        xr, yr, pr, ci, si = _estimate_reference(i, ex, ey, epsi, valid, pdx, pdy, psi_off)
        _law_env(i, a, -xr, -yr, ci, si, -pr, eu[i], ev[i], er[i], not valid[i], pdx, pdy, gain, model, fa, fb,
                 prev, d, reset_all or reset[i], F)


#: the passes, serial and on numba's threads (per env the same arithmetic: the same bits)
_reference_serial = njit(cache=True)(_reference_all)
_reference_threads = recompiled(_reference_all, "_reference_par", cache=True, parallel=True)
_law_serial = njit(cache=True)(_law_pass)
_law_threads = recompiled(_law_pass, "_law_par", cache=True, parallel=True)
_est_reference_serial = njit(cache=True)(_estimate_reference_all)
_est_reference_threads = recompiled(_estimate_reference_all, "_est_reference_par", cache=True, parallel=True)
_est_law_serial = njit(cache=True)(_estimate_law_pass)
_est_law_threads = recompiled(_estimate_law_pass, "_est_law_par", cache=True, parallel=True)
#: batches from this many envs run the passes on numba's threads (as the vector env's steps)
THREADED_MIN_ENVS = 256


def _passes(n: int):
    """(reference pass, law pass, estimate reference pass, estimate law pass) for a batch of n envs."""
    if n >= THREADED_MIN_ENVS and numba.get_num_threads() > 1:
        return _reference_threads, _law_threads, _est_reference_threads, _est_law_threads
    return _reference_serial, _law_serial, _est_reference_serial, _est_law_serial


@njit(cache=True)
def _same_bits(a, b):
    """Whether two flat int64 arrays of one length hold the same bits."""
    acc = 0
    for i in range(a.size):
        acc |= a[i] ^ b[i]
    return acc == 0


def _fusable(obs, dtypes=(np.float64,)) -> bool:
    """A 2-D batch of a known layout and of one of ``dtypes`` (float64: what the compiled passes
    read)."""
    return (isinstance(obs, np.ndarray) and obs.ndim == 2 and obs.dtype in dtypes
            and obs.shape[1] in LAYOUTS)


class HierarchicalController(ScriptedPolicy):
    """The predictive robust tracking controller and its ablations (Table 1).

    Args:
        spec: the env's TaskSpec (tau, p_d, psi_d, nominal model, dt, force limits).
        prediction: delay prediction (Sec. 3.3) on/off.
        robust: robust terms rho sat(e/phi) in (32)-(34) on/off.
        gains: :class:`Gains`; defaults shared by all variants.
        name: label used in tables.
        estimator: ours, not the paper's: a :class:`~controllers.estimator.TargetEstimator`
            whose present estimate replaces the predictor (13)-(17) (``prediction`` is then
            ignored); None (the paper's four) keeps eqs. (13)-(17).
        disturbance_observer: ours, not the paper's: a
            :class:`~controllers.disturbance.DisturbanceObserver` whose estimate is
            subtracted from (32)-(34); None (the paper's four) leaves the law as printed.
    """

    def __init__(self, spec: TaskSpec, *, prediction: bool = True, robust: bool = True,
                 gains: Gains | None = None, name: str | None = None,
                 estimator: TargetEstimator | None = None,
                 disturbance_observer: DisturbanceObserver | None = None) -> None:
        super().__init__(spec)
        if estimator is not None and not isinstance(estimator, TargetEstimator):
            raise ValueError(f"estimator={estimator!r} is invalid: must be a TargetEstimator or None")
        if disturbance_observer is not None and not isinstance(disturbance_observer, DisturbanceObserver):
            raise ValueError(f"disturbance_observer={disturbance_observer!r} is invalid: must be a "
                             f"DisturbanceObserver or None")
        self.prediction = bool(prediction)
        self.robust = bool(robust)
        self.gains = gains if gains is not None else Gains()
        self.name = name or f"hierarchical(prediction={self.prediction}, robust={self.robust})"
        self.estimator = estimator
        self.disturbance_observer = disturbance_observer
        self._diff = FilteredDerivative(spec.dt, self.gains.derivative_tc)
        #: run the compiled passes where they apply (False: the numpy composition, as a reference)
        self._fused = True
        #: (observation key, prediction, spec, ref, cos psi_hat, sin psi_hat, -psi_ref) of the last reference()
        self._cache: tuple | None = None

    def _uses_fused(self, obs) -> bool:
        return (self._fused and self.estimator is None and self.disturbance_observer is None and _fusable(obs)
                and type(self)._generate is HierarchicalController._generate)

    def _uses_fused_estimate(self, obs, dtypes=(np.float64,)) -> bool:
        """The compiled passes on the estimator's output (the estimator itself runs as always)."""
        dob = self.disturbance_observer
        return (self._fused and self.estimator is not None and _fusable(obs, dtypes)
                and type(self)._estimate is HierarchicalController._estimate
                and (dob is None or dob.fusable))

    def _law_constants(self, n: int) -> tuple[np.ndarray, np.ndarray, bool]:
        """The compiled law's gain and model vectors (see :func:`_law_pass`), and whether the
        filtered derivative restarts everywhere (its state made ready for n envs)."""
        diff = self._diff
        reset_all = diff.prev is None or diff.prev.shape != (n, 3)
        if reset_all:
            diff.prev, diff.d = np.empty((n, 3)), np.zeros((n, 3))
        g, nom = self.gains, self.spec.nominal
        rho = g.rho if self.robust else (0.0, 0.0, 0.0)
        gain = np.array([-g.K_p, -g.K_psi, g.K_u, g.K_v, g.K_r, *rho, *g.phi], dtype=np.float64)
        model = np.array([nom.m, nom.I_z, nom.X_u, nom.Y_v, nom.N_r], dtype=np.float64)
        return gain, model, reset_all

    def _estimate_forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        """:meth:`forces` with an estimator, compiled: the same operations as the numpy
        composition (``_fused = False``) on the estimator's present estimate."""
        n = obs.shape[0]
        est = self.estimator.step(obs, reset_mask, commit=True, with_cov=False, copy=False)  # (read only)
        diff, p_d = self._diff, self.spec.p_d
        gain, model, reset_all = self._law_constants(n)
        F = np.empty((n, 3))
        _passes(n)[3](obs, est.rel_x, est.rel_y, est.rel_psi, est.u, est.v, est.r, est.valid, float(p_d[0]),
                      float(p_d[1]), float(self.spec.psi_d), gain, model, diff.a, diff.b, diff.prev, diff.d,
                      reset_mask, reset_all, F)
        if self.disturbance_observer is not None:
            self.disturbance_observer.correct(obs, reset_mask, F)
        return F

    def _fused_reference(self, a: np.ndarray):
        """(ref (N, 3), cos psi_hat, sin psi_hat, -psi_ref) of the batch ``a``: :meth:`_generate`
        compiled, each libm function called once per env."""
        n = a.shape[0]
        v1 = a.shape[1] == OBS_DIM_V1
        ref, neg, c, s = np.empty((n, 3)), np.empty(n), np.empty(n), np.empty(n)
        p_d = self.spec.p_d
        _passes(n)[0](a, self.prediction, float(self.spec.delay_s), _AGE if v1 else -1, float(p_d[0]), float(p_d[1]),
                      float(self.spec.psi_d), _HAS if v1 else -1, ref, neg, c, s)
        return ref, c, s, neg

    def _cached_reference(self, a: np.ndarray):
        """The last :meth:`reference`'s values if it was given the same bits (and settings)."""
        c = self._cache
        if (c is not None and c[1] == self.prediction and c[2] is self.spec and c[0].shape == a.shape
                and _same_bits(c[0].view(np.int64).reshape(-1), a.view(np.int64).reshape(-1))):
            return c[3:]
        return None

    def _fused_forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        n = obs.shape[0]
        cached = self._cached_reference(obs)
        ref, c, s, neg = cached if cached is not None else self._fused_reference(obs)
        diff, p_d = self._diff, self.spec.p_d
        gain, model, reset_all = self._law_constants(n)
        F = np.empty((n, 3))
        _passes(n)[1](obs, ref, c, s, neg, _HAS if obs.shape[1] == OBS_DIM_V1 else -1, float(p_d[0]), float(p_d[1]),
                      gain, model, diff.a, diff.b, diff.prev, diff.d, reset_mask, reset_all, F)
        return F

    def _generate(self, o: dict[str, np.ndarray]):
        pred = predict_target(o, prediction_horizon(o, self.spec.delay_s), self.prediction)
        ref = reference_point(pred[0], pred[1], pred[2], self.spec.p_d, self.spec.psi_d)
        return pred, zero_where(ref, no_packet_mask(o))

    def _estimate(self, obs: np.ndarray, reset_mask: np.ndarray | None, commit: bool):
        """Prediction and reference from the estimator (holding position without a fix)."""
        est = self.estimator.step(obs, reset_mask, commit=commit, with_cov=False)
        pred = est.as_prediction()
        hold = ~est.valid
        ref = reference_point(pred[0], pred[1], pred[2], self.spec.p_d, self.spec.psi_d)
        return pred, zero_where(ref, hold), hold

    def reference(self, observation) -> np.ndarray:
        obs = np.atleast_2d(observation)
        if self.estimator is not None:
            if obs.dtype not in (np.float64, np.float32):
                obs = np.asarray(obs, dtype=np.float64)
            if self._uses_fused_estimate(obs, (np.float64, np.float32)):
                # the estimator converts a float32 batch itself: its float64 copy is then private,
                # and the peek keeps it without another copy
                est = self.estimator.step(obs, None, commit=False, with_cov=False)
                ref = np.empty((obs.shape[0], 3))
                p_d = self.spec.p_d
                _passes(obs.shape[0])[2](est.rel_x, est.rel_y, est.rel_psi, est.valid, float(p_d[0]), float(p_d[1]),
                                         float(self.spec.psi_d), ref)
                return ref
            _, ref, _ = self._estimate(np.asarray(obs, dtype=np.float64), None, commit=False)
            return np.stack(ref, axis=-1)
        a = np.asarray(obs, dtype=np.float64)
        if self._uses_fused(a):
            out = self._fused_reference(a)
            key = a.copy() if np.may_share_memory(a, obs) else a  # a private copy of the bits
            self._cache = (key, self.prediction, self.spec, *out)
            return out[0].copy()
        o = decode(obs)
        _, ref = self._generate(o)
        return np.stack(ref, axis=-1)

    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        plain, on_estimate = self._uses_fused(obs), self._uses_fused_estimate(obs)
        if plain or on_estimate:
            n, prev = obs.shape[0], self._diff.prev
            mask_ok = isinstance(reset_mask, np.ndarray) and reset_mask.dtype == np.bool_ and reset_mask.shape == (n,)
            if mask_ok and (prev is None or prev.shape == (n, 3) or reset_mask.any()):
                return self._fused_forces(obs, reset_mask) if plain else self._estimate_forces(obs, reset_mask)
            # (another mask type, or a batch of another size without a reset: the numpy composition)
        o = decode(obs)
        if self.estimator is None:
            pred, ref = self._generate(o)
            hold = no_packet_mask(o)
        else:
            pred, ref, hold = self._estimate(obs, reset_mask, commit=True)
        desired = zero_where(outer_loop(ref, pred, self.spec.p_d, self.gains), hold)
        d = np.stack(desired, axis=-1)
        if reset_mask.any() or self._diff.prev is None:
            self._diff.reset(reset_mask, d)
        d_dot = self._diff(d)
        F = inner_loop(o, desired, (d_dot[:, 0], d_dot[:, 1], d_dot[:, 2]), self.spec.nominal,
                       self.gains, self.robust)
        F = np.stack(F, axis=-1)
        dob = self.disturbance_observer
        if dob is not None:
            nu = np.stack([o["u"], o["v"], o["r"]], axis=-1)
            F = F - dob.update(nu, np.stack([o["current_u"], o["current_v"]], axis=-1), reset_mask)
            dob.applied(F)
        return F
