"""The batched simulator shared by the single env and the vector env.

``BatchSim`` owns the arrays of :mod:`auv_follow_env.dynamics` for N envs, draws each
episode's random parameters from that env's own generator, and calls the kernels. The
Gymnasium shells (``AUVFollowEnv``, ``AUVFollowVectorEnv``) only validate input and
format output.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from types import SimpleNamespace

import numpy as np

from auv_follow_env import dynamics as dyn
from auv_follow_env.kernel_one import packed_arrays, reset_one, step_one
from auv_follow_env.layout import OBS_DIM, OBS_DIM_V1
from auv_follow_env.params import LATENCY_MODELS, RANGEABLE, Condition, EnvConfig, VehicleParams
from auv_follow_env.warm import guard_numba_cache

# a numba cache file that cannot be read back is reported, removed and recompiled (not an
# UnpicklingError at every first call); both envs load their kernels through this module
guard_numba_cache()

__all__ = ["BatchSim", "param_row", "sample_params", "params_from_uniforms", "sample_params_v1",
           "sample_params_v1_many", "link_row", "config_vector", "queue_capacity", "SINCOS", "check_sincos"]

TWO_PI = 2.0 * math.pi
#: range of the current's period [s] (ours: "slowly varying", tens of seconds)
CURRENT_PERIOD_RANGE = (40.0, 80.0)


def param_row(*, vehicle: VehicleParams, target_speed: float = 0.0, surge_amp: float = 0.0,
              surge_period: float = 1.0, surge_phase: float = 0.0, yaw_rate_amp: float = 0.0,
              yaw_period: float = 1.0, yaw_phase: float = 0.0,
              current_x: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
              current_y: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
              disturbance: tuple[tuple[float, float, float, float], ...] = ((0.0,) * 4,) * 3,
              latency_steps: int = 0) -> np.ndarray:
    """One row of the kernel's parameter array, from explicit values.

    ``current_x``/``current_y`` are (mean [m/s], amplitude [m/s], omega [rad/s], phase);
    ``disturbance`` is three rows (u, v, r) of (amp1, phase1, amp2, phase2) in N / N m;
    ``latency_steps`` the constant delay tau / dt of the v0 link.
    """
    row = _param_rows(np.zeros(dyn.NP), vehicle, target_speed, surge_amp, surge_period, yaw_rate_amp,
                      yaw_period, latency_steps)
    row[dyn.P_TPU], row[dyn.P_TPR] = surge_phase, yaw_phase
    row[dyn.P_CX:dyn.P_CX + 4] = current_x
    row[dyn.P_CY:dyn.P_CY + 4] = current_y
    row[dyn.P_D:dyn.P_D + 12] = np.asarray(disturbance, dtype=np.float64).ravel()
    return row


def _param_rows(rows: np.ndarray, vehicle, target_speed, surge_amp, surge_period, yaw_rate_amp, yaw_period,
                latency_steps) -> np.ndarray:
    """:func:`param_row`'s vehicle, target and v0 link columns in the zeroed ``rows`` ((NP,) or (n, NP);
    each value a float or an (n,) array of per-row values); returns ``rows``."""
    for col, v in ((dyn.P_M, vehicle.m), (dyn.P_IZ, vehicle.I_z), (dyn.P_XU, vehicle.X_u), (dyn.P_YV, vehicle.Y_v),
                   (dyn.P_NR, vehicle.N_r), (dyn.P_TV, target_speed), (dyn.P_TAU, surge_amp),
                   (dyn.P_TWU, TWO_PI / surge_period), (dyn.P_TAR, yaw_rate_amp), (dyn.P_TWR, TWO_PI / yaw_period)):
        rows[..., col] = v
    # v0: no random processes, unbounded target, ideal thrusters, a packet every step with the
    # constant latency set by link_row (or config_vector's delay)
    for col in (dyn.P_OUU_A, dyn.P_OUR_A, dyn.P_CS_A, dyn.P_DN_A, dyn.P_TH_ALPHA, dyn.P_PER, dyn.P_LAT_CORR):
        rows[..., col] = 1.0
    rows[..., dyn.P_ULO] = -math.inf
    for col in (dyn.P_UHI, dyn.P_RMAX, dyn.P_TH_RATE):
        rows[..., col] = math.inf
    rows[..., dyn.P_LAT_MEAN] = latency_steps
    return rows


def _each(f, x):
    """f (a ``math`` function of one float) of x, or of each element of the array x: the same
    libm call per element (numpy's own SIMD exp may differ from it in the last bit)."""
    if isinstance(x, np.ndarray):
        return np.array([f(v) for v in x.tolist()], dtype=np.float64)
    return f(x)


def link_row(row: np.ndarray, c: Condition, dt: float, vehicle: VehicleParams) -> np.ndarray:
    """Write condition ``c``'s processes, thrusters and link into a param row (in place).

    Also for n rows at once ((n, NP), with ``c`` and ``vehicle`` giving a float or an (n,) array
    per field: :func:`sample_params_v1_many`)."""
    def put(col: int, v) -> None:
        row[..., col] = v

    put(dyn.P_OUU_STD, c.target_speed_std)
    put(dyn.P_OUU_A, _each(math.exp, -dt / c.target_speed_corr_s))
    put(dyn.P_OUR_STD, c.target_yaw_rate_std)
    put(dyn.P_OUR_A, _each(math.exp, -dt / c.target_yaw_rate_corr_s))
    put(dyn.P_ULO, c.target_speed_min)
    put(dyn.P_UHI, c.target_speed_max)
    put(dyn.P_RMAX, c.target_yaw_rate_max)
    put(dyn.P_CS_MEAN, c.current_speed)
    put(dyn.P_CS_STD, c.current_speed_std)
    put(dyn.P_CS_A, _each(math.exp, -dt / c.current_corr_s))
    put(dyn.P_CD_STEP, c.current_direction_drift * math.sqrt(dt))
    put(dyn.P_DN, c.disturbance_noise_u * vehicle.m)
    put(dyn.P_DN + 1, c.disturbance_noise_v * vehicle.m)
    put(dyn.P_DN + 2, c.disturbance_noise_r * vehicle.I_z)
    put(dyn.P_DN_A, _each(math.exp, -dt / c.disturbance_corr_s))
    put(dyn.P_TH_ALPHA, _each(lambda tc: 1.0 - math.exp(-dt / tc) if tc > 0 else 1.0, c.thruster_tc_s))
    put(dyn.P_TH_RATE, c.thruster_rate * dt)
    put(dyn.P_PER, c.update_period_s / dt)
    put(dyn.P_JIT, c.period_jitter_s / dt)
    put(dyn.P_LAT_KIND, LATENCY_MODELS.index(c.latency_model))
    put(dyn.P_LAT_MEAN, c.latency_s / dt)
    put(dyn.P_LAT_SPREAD, c.latency_spread_s / dt)
    put(dyn.P_LAT_CORR, c.latency_corr_s / dt)
    put(dyn.P_LOSS, c.loss_prob)
    put(dyn.P_GB, c.burst_p_good_bad)
    put(dyn.P_BG, c.burst_p_bad_good)
    put(dyn.P_LOSS_BAD, c.burst_loss_bad)
    put(dyn.P_NS0, c.fix_sigma_m)
    put(dyn.P_NSK, c.fix_sigma_per_m)
    put(dyn.P_NPSI, c.heading_sigma_rad)
    put(dyn.P_NVEL, c.velocity_sigma_mps)
    put(dyn.P_NYAW, c.yaw_rate_sigma_radps)
    # a leader target: its modes set the speed and turn rate (the tones' base speed is zeroed)
    modes = np.asarray(c.leader_modes, dtype=np.float64)
    if np.any(modes > 0):
        row[..., dyn.P_TV] = np.where(modes > 0, 0.0, row[..., dyn.P_TV])
    put(dyn.P_LD_MODES, c.leader_modes)
    put(dyn.P_LD_SURVEY, c.leader_survey_share)
    put(dyn.P_LD_UC, c.leader_cruise_speed)
    put(dyn.P_LD_RT, c.leader_turn_rate)
    put(dyn.P_LD_MC, c.leader_cruise_mean_s)
    put(dyn.P_LD_MT, c.leader_turn_mean_s)
    put(dyn.P_LD_UL, c.leader_loiter_speed)
    put(dyn.P_LD_ML, c.leader_loiter_mean_s)
    put(dyn.P_LD_US, c.leader_sprint_speed)
    put(dyn.P_LD_MS, c.leader_sprint_mean_s)
    put(dyn.P_LD_LEG, c.leader_leg_m)
    put(dyn.P_LD_RS, c.leader_uturn_rate)
    put(dyn.P_LD_AU, _each(math.exp, -dt / c.leader_speed_lag_s))
    put(dyn.P_LD_AR, _each(math.exp, -dt / c.leader_rate_lag_s))
    put(dyn.P_LD_TR, c.leader_rate_lag_s)
    put(dyn.P_LD_WU, c.leader_wobble_speed)
    put(dyn.P_LD_WR, c.leader_wobble_rate)
    put(dyn.P_LD_WA, _each(math.exp, -dt / c.leader_wobble_corr_s))
    put(dyn.P_LD_DT, dt)
    put(dyn.P_OUT_P, c.outlier_share)
    put(dyn.P_OUT_S, c.outlier_scale_m)
    return row


def sample_params(config: EnvConfig, rng: np.random.Generator, *, vehicle: VehicleParams | None = None,
                  target: tuple[float, float, float] | None = None,
                  current: tuple[tuple[float, float], tuple[float, float]] | None = None) -> np.ndarray:
    """Draw one episode's parameters from ``rng`` (always exactly 12 uniforms, in order).

    Random: the target's two manoeuvre phases, the current's periods and phases, and the
    six disturbance-tone phases. Fixed by the config: everything else, unless given here
    (v1 draws them per reset): ``vehicle`` (the true plant), ``target`` = (v_bar, a_u, a_r),
    ``current`` = the (min, max) ranges of the x and y tone current.
    """
    return params_from_uniforms(config, rng.random(12)[None, :], vehicle=vehicle, target=target,
                                current=current)[0]


def params_from_uniforms(config: EnvConfig, u: np.ndarray, *, vehicle: VehicleParams | None = None,
                         target: tuple[float, float, float] | None = None,
                         current: tuple[tuple[float, float], tuple[float, float]] | None = None) -> np.ndarray:
    """The param rows (n, NP) of n episodes from their 12 uniforms each, ``u`` (n, 12), in
    :func:`sample_params`' order (element-wise arithmetic: row j equals the scalar computation
    on ``u[j]``, so a batch of resets gives the same rows as one reset at a time)."""
    tp = config.scenario.target
    lvl = config.disturbance
    veh = config.true_vehicle if vehicle is None else vehicle
    speed, surge_amp, yaw_amp = (tp.speed, tp.surge_amp, tp.yaw_rate_amp) if target is None else target
    cur_x, cur_y = (lvl.current_x, lvl.current_y) if current is None else current
    base = _base_row(veh, float(speed), float(surge_amp), float(tp.surge_period), float(yaw_amp),
                     float(tp.yaw_period), config.delay_steps, tuple(cur_x), tuple(cur_y), tuple(lvl.peaks))
    rows = np.empty((u.shape[0], dyn.NP))
    rows[:] = base
    return _set_uniforms(rows, u)


#: the param columns set from the 12 uniforms: phases (2 pi u) and the current's two tone
#: frequencies (2 pi / period, the period uniform in CURRENT_PERIOD_RANGE), with the uniforms' index
_PHASE_COLS = [dyn.P_TPU, dyn.P_TPR, dyn.P_CX + 3, dyn.P_CY + 3] + [dyn.P_D + 4 * c + k for c in range(3)
                                                                  for k in (1, 3)]
_PHASE_U = [0, 1, 3, 5, 6, 7, 8, 9, 10, 11]
_PERIOD_COLS = [dyn.P_CX + 2, dyn.P_CY + 2]
_PERIOD_U = [2, 4]


@functools.lru_cache(maxsize=256)
def _base_row(veh: VehicleParams, speed: float, surge_amp: float, surge_period: float, yaw_amp: float,
              yaw_period: float, delay_steps: int, cur_x: tuple, cur_y: tuple, peaks: tuple) -> np.ndarray:
    """The part of a v0 param row that does not depend on the uniforms (read-only, cached:
    a reset of a few envs would otherwise spend most of its time rebuilding it)."""
    row = _base_rows(np.zeros(dyn.NP), veh, speed, surge_amp, surge_period, yaw_amp, yaw_period, delay_steps,
                     cur_x, cur_y, peaks)
    row.flags.writeable = False
    return row


def _base_rows(rows: np.ndarray, veh, speed, surge_amp, surge_period: float, yaw_amp, yaw_period: float,
               delay_steps: int, cur_x: tuple, cur_y: tuple, peaks: tuple) -> np.ndarray:
    """:func:`_base_row` into the zeroed ``rows`` ((NP,) or (n, NP); the vehicle's fields, speed and
    amplitudes floats or (n,) arrays); returns ``rows``."""
    _param_rows(rows, veh, speed, surge_amp, surge_period, yaw_amp, yaw_period, delay_steps)
    for col, (a, b) in ((dyn.P_CX, cur_x), (dyn.P_CY, cur_y)):
        rows[..., col] = 0.5 * (a + b)
        rows[..., col + 1] = 0.5 * (b - a)
    scale = (veh.m, veh.m, veh.I_z)  # Table 3 peaks read per unit mass (docs/paper_notes.md)
    w1, w2 = dyn.DIST_WEIGHT
    for c, (pk, sc) in enumerate(zip(peaks, scale, strict=True)):
        rows[..., dyn.P_D + 4 * c] = w1 * pk * sc
        rows[..., dyn.P_D + 4 * c + 2] = w2 * pk * sc
    return rows


def _set_uniforms(rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The columns of ``rows`` (n, NP) set from the episodes' 12 uniforms ``u`` (n, 12)."""
    lo, hi = CURRENT_PERIOD_RANGE
    rows[:, _PHASE_COLS] = TWO_PI * u[:, _PHASE_U]
    rows[:, _PERIOD_COLS] = TWO_PI / (lo + (hi - lo) * u[:, _PERIOD_U])
    return rows


def sample_params_v1(config: EnvConfig, rng: np.random.Generator) -> tuple[np.ndarray, int, float, dict]:
    """Draw one v1 episode from ``rng``: (param row, kernel seed, current direction, condition).

    Order of the draws (fixed, so a seed means the same episode everywhere): one uniform per
    ranged field (in :data:`~auv_follow_env.params.RANGEABLE` order), v0's 12 uniforms
    (phases, current periods), one uniform for the Gauss-Markov current's direction, and the
    64-bit seed of the env's in-kernel generator (link, noise, random processes). With no
    ranges, the phases equal those of the v0 env with the same seed.

    The reference (one episode, through :class:`~auv_follow_env.params.Condition`, which
    validates the draw); the envs use :func:`sample_params_v1_many`, which gives the same values.
    """
    c = config.condition
    assert c is not None
    drawn = {}
    for name in RANGEABLE:
        if name in config.ranges:
            lo, hi = config.ranges[name]
            drawn[name] = lo + (hi - lo) * float(rng.random())
    mismatch = drawn.pop("mismatch", config.mismatch)
    if drawn:
        c = dataclasses.replace(c, **drawn)  # validates the drawn combination
    vehicle = config.nominal.with_mismatch(mismatch)
    lvl = config.disturbance
    current = (c.current_x or lvl.current_x, c.current_y or lvl.current_y)
    row = sample_params(config, rng, vehicle=vehicle, target=(c.target_speed, c.target_surge_amp,
                                                              c.target_yaw_rate_amp), current=current)
    direction = TWO_PI * float(rng.random())
    if c.current_direction_rad is not None:
        direction = float(c.current_direction_rad)
    seed = int(rng.integers(0, 2**63, dtype=np.int64))
    link_row(row, c, config.dt, vehicle)
    condition = {**c.as_dict(), "mismatch": mismatch, "current_direction_rad": direction,
                 "current_x": current[0], "current_y": current[1]}
    return row, seed, direction, condition


def _numeric(v: object) -> bool:
    """Whether a condition value is a number (or an array of them) rather than an object."""
    return isinstance(v, np.ndarray) or (isinstance(v, (int, float)) and not isinstance(v, bool))


@functools.cache
def _field_names(cls: type) -> tuple[str, ...]:
    """The field names of the dataclass ``cls``, in order."""
    return tuple(f.name for f in dataclasses.fields(cls))


class _Drawn:
    """The condition of n episodes, field by field: a drawn field's (n,) values, else the fixed value.
    (Plain instance attributes: a reset of a few envs reads about ninety of them.)"""

    def __init__(self, c: Condition | VehicleParams, drawn: dict[str, object]) -> None:
        self.__dict__.update({name: getattr(c, name) for name in _field_names(type(c))})
        self.__dict__.update(drawn)
        self.__dict__["_c"] = c

    def __getattr__(self, name: str):  # (only for what is not a field: c's properties)
        return getattr(self.__dict__["_c"], name)


def sample_params_v1_many(config: EnvConfig, rngs: list[np.random.Generator]
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, object]]:
    """:func:`sample_params_v1` for n episodes, env j's from ``rngs[j]`` (the same draws in the
    same order, and the same arithmetic column by column, so row j equals
    ``sample_params_v1(config, rngs[j])``'s; tests/test_link.py). The draws' combination is not
    validated again: ``make_config`` refused any ranges under which a draw could break a rule.

    Returns (rows (n, NP), seeds (n,) int64, directions (n,), condition): the condition maps
    each field of ``info["condition"]`` to a float, a fixed object, or an (n,) array of draws.
    """
    c = config.condition
    assert c is not None
    names = [name for name in RANGEABLE if name in config.ranges]
    n, q = len(rngs), len(names)
    u = np.empty((n, q + 13))
    seeds = np.empty(n, dtype=np.int64)
    for j, rng in enumerate(rngs):
        u[j] = rng.random(q + 13)  # (the same stream as q + 13 calls of rng.random())
        seeds[j] = rng.integers(0, 2**63, dtype=np.int64)
    drawn: dict[str, np.ndarray] = {}
    for j, name in enumerate(names):
        lo, hi = config.ranges[name]
        drawn[name] = lo + (hi - lo) * u[:, j]
    mismatch = drawn.pop("mismatch", config.mismatch)
    nom = config.nominal
    k = 1.0 + mismatch  # VehicleParams.with_mismatch, per episode
    vehicle = _Drawn(nom, {"X_u": nom.X_u * k, "Y_v": nom.Y_v * k, "N_r": nom.N_r * k})
    cc = _Drawn(c, drawn)
    lvl = config.disturbance
    current = (c.current_x or lvl.current_x, c.current_y or lvl.current_y)
    tp = config.scenario.target
    rows = _base_rows(np.zeros((n, dyn.NP)), vehicle, cc.target_speed, cc.target_surge_amp, float(tp.surge_period),
                      cc.target_yaw_rate_amp, float(tp.yaw_period), config.delay_steps, tuple(current[0]),
                      tuple(current[1]), tuple(lvl.peaks))
    _set_uniforms(rows, u[:, q:q + 12])
    directions = TWO_PI * u[:, q + 12]
    if cc.current_direction_rad is not None:
        directions = np.broadcast_to(np.asarray(cc.current_direction_rad, dtype=np.float64), (n,)).copy()
    link_row(rows, cc, config.dt, vehicle)
    condition = {**{name: getattr(cc, name) for name in _field_names(type(c))}, "mismatch": mismatch,
                 "current_direction_rad": directions, "current_x": current[0], "current_y": current[1]}
    return rows, seeds, directions, condition


#: the link's packet counters (:meth:`BatchSim.link_stats`) and their columns in ``proc``
LINK_COUNTERS = {"sent": dyn.R_SENT, "lost": dyn.R_LOST, "arrived": dyn.R_ARRIVED, "discarded": dyn.R_DISCARDED,
                 "overflow": dyn.R_OVERFLOW}
#: the arrays of :meth:`BatchSim.step_call`'s leading args, in the step kernel's order
STEP_ARRAYS = ("state", "k", "proc", "queue", "rs", "params", "cfg", "obs", "truth", "err_hist", "err_stage",
               "rew", "term")
#: the arrays a reset writes (dynamics.reset_kernel): what a reset made ahead copies in
_RESET_ARRAYS = ("state", "k", "proc", "queue", "rs", "params", "obs", "truth")


class _Episodes:
    """The episodes of N envs: what :meth:`BatchSim.reset` draws and starts, and each env's
    v1 condition.

    Each env's episodes are drawn from its own generator, in order. With ``ahead`` (the vector
    env's BatchSim) an env's next episode is drawn and started ahead: after an autoreset the env
    waits in a list of pending envs, and once the list is long (N / 8 envs, at most 256) the
    next episode of each is drawn in one call (:func:`sample_params_v1_many`; v0: twelve
    uniforms each) and started in a shadow copy of the sim's arrays by one call of the reset
    kernel (full blocks of envs; on numba's threads where the vector env steps on them). An
    autoreset then copies the env's rows in. Nothing of a reset depends on the episode before
    it, so this changes no result: the target, link and processes' warm-up of the next episode
    is the same computation, done in bigger blocks, earlier. A draw made ahead is used only if
    the env resets with the same generator object it came from (a new seed makes a new
    generator: then the episode is drawn and started at the reset), so every env plays the
    same episodes, in the same order, as if each were drawn at its reset (tests/test_link.py).
    Without ``ahead`` (the single env, whose generator is Gymnasium's ``np_random``) nothing
    is drawn early.
    """

    def __init__(self, sim: BatchSim, *, ahead: bool) -> None:
        self.sim, self.config, self.n, self.ahead = sim, sim.config, sim.num_envs, ahead
        self.v1 = sim.v1
        self.batch = max(1, min(256, self.n // 8))  #: pending envs that trigger a draw ahead
        #: reset kernel of the starts ahead and of resets of two blocks or more: (kernel, extra args)
        #: (the vector env sets the threaded one when it steps on threads)
        self.kernel: tuple = (dyn.reset_kernel, ())
        self.keys: list[str] = []  #: v1: the condition's fields, in info["condition"]'s order
        self.numeric: list[str] = []  #: those with numbers (columns of cond)
        self.col: dict[str, int] = {}  #: their column in cond
        self.fixed: dict[str, object] = {}  #: the others (the same for every episode of a config)
        self.cond: np.ndarray | None = None  #: (N, len(numeric)): each env's present condition
        self.gen: list[np.random.Generator | None] = [None] * self.n  #: each env's generator
        self.ready = np.zeros(self.n, dtype=np.bool_)  #: whether the env's next episode is started ahead
        self.pending: list[int] = []
        self.shadow: SimpleNamespace | None = None  #: the arrays of the episodes started ahead (lazily)
        self.next_cond: np.ndarray | None = None

    def _draw(self, rngs: list[np.random.Generator]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(rows, seeds, directions, condition block) of the next episode of each generator."""
        if not self.v1:  # v0: each env's 12 uniforms from its own generator, then the rows at once
            rows = params_from_uniforms(self.config, np.array([rng.random(12) for rng in rngs]))
            return rows, np.zeros(len(rngs), dtype=np.int64), np.zeros(len(rngs)), None
        rows, seeds, dirs, cond = sample_params_v1_many(self.config, rngs)
        if not self.keys:
            self.keys = list(cond)
            self.numeric = [k for k in cond if _numeric(cond[k])]
            self.col = {key: j for j, key in enumerate(self.numeric)}
            self.fixed = {k: v for k, v in cond.items() if not _numeric(v)}
            self.cond = np.full((self.n, len(self.numeric)), np.nan)
            self.next_cond = np.full((self.n, len(self.numeric)), np.nan)
        block = np.empty((len(rngs), len(self.numeric)))
        for j, key in enumerate(self.numeric):
            block[:, j] = cond[key]
        return rows, seeds, dirs, block

    @staticmethod
    def _reset(a, kernel: tuple, idx: np.ndarray, seeds: np.ndarray, dirs: np.ndarray) -> None:
        """The reset kernel on the envs ``idx`` of ``a`` (a BatchSim or the shadow arrays)."""
        fn, extra = kernel
        fn(a.state, a.k, a.proc, a.queue, a.rs, a.params, a.cfg, idx, seeds, dirs, a.obs, a.truth, *extra)

    def start(self, idx: np.ndarray, rngs: list[np.random.Generator], auto: bool) -> None:
        """Start the new episodes of envs ``idx`` (env idx[j]'s drawn from rngs[j]) in the sim's
        arrays; record their conditions. ``auto``: an autoreset, after which the envs' next
        episodes are started ahead (after an explicit reset they are not: a caller that
        reseeds every episode, as the evaluations do, would throw them away)."""
        sim = self.sim
        have = np.array([self.ready[i] and self.gen[i] is g for i, g in zip(idx.tolist(), rngs, strict=True)],
                        dtype=np.bool_)
        need = np.flatnonzero(~have)
        if need.size:
            ids = idx[need]
            rows, seeds, dirs, c = self._draw([rngs[j] for j in need])
            sim.params[ids] = rows
            if self.v1:
                self.cond[ids] = c
            if sim.buf is not None:  # one packed env: the one-lane kernel (kernel_one)
                if ids[0] != 0:
                    raise ValueError(f"env index {ids[0]} out of range for one env")
                reset_one(sim.buf, int(seeds[0]), float(dirs[0]))
            else:
                self._reset(sim, self.kernel if ids.size >= 2 * dyn.BLOCK else (dyn.reset_kernel, ()), ids, seeds,
                            dirs)
        if have.any():
            took = idx[have]
            for name in _RESET_ARRAYS:
                getattr(sim, name)[took] = getattr(self.shadow, name)[took]
            if self.v1:
                self.cond[took] = self.next_cond[took]
        self.ready[idx] = False
        for i, g in zip(idx.tolist(), rngs, strict=True):
            self.gen[i] = g
        if self.ahead and auto:
            self.pending.extend(idx.tolist())
            if len(self.pending) >= self.batch:
                self._start_ahead()

    def _start_ahead(self) -> None:
        """Draw and start the next episode of every pending env, in one call each."""
        todo = np.array(sorted({i for i in self.pending if not self.ready[i]}), dtype=np.int64)
        self.pending = []
        if not todo.size:
            return
        if self.shadow is None:
            self.shadow = SimpleNamespace(cfg=self.sim.cfg, **{name: np.zeros_like(getattr(self.sim, name))
                                                                 for name in _RESET_ARRAYS})
        rows, seeds, dirs, c = self._draw([self.gen[i] for i in todo.tolist()])
        self.shadow.params[todo] = rows
        if self.v1:
            self.next_cond[todo] = c
        self._reset(self.shadow, self.kernel, todo, seeds, dirs)
        self.ready[todo] = True

    def condition(self, i: int) -> dict[str, object]:
        col = self.col
        return {key: float(self.cond[i, col[key]]) if key in col else self.fixed[key] for key in self.keys}

    def conditions(self, mask: np.ndarray) -> dict[str, np.ndarray]:
        ids = np.flatnonzero(mask)
        block = np.full(self.cond.shape, np.nan)
        block[ids] = self.cond[ids]
        col = self.col
        out = {}
        for key in self.keys:
            if key in col:
                out[key] = block[:, col[key]]
            elif _is_number_tuple(self.fixed[key]):
                # a fixed range (current_x, current_y): one (lo, hi) row per env, NaN elsewhere, so
                # batched readers (TorchRL) see a float array of shape (N, 2) led by the env axis
                arr = np.full((self.n, len(self.fixed[key])), np.nan)
                arr[mask] = np.asarray(self.fixed[key], dtype=np.float64)
                out[key] = arr
            else:
                arr = np.empty(self.n, dtype=object)  # (None everywhere)
                one = np.empty(1, dtype=object)
                one[0] = self.fixed[key]
                arr[mask] = one
                out[key] = arr
        return out


def _is_number_tuple(value: object) -> bool:
    return (isinstance(value, tuple) and len(value) > 0
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))


def queue_capacity(config: EnvConfig) -> int:
    """Packets that can be in flight at once (v0: tau / dt + 2; v1: from the largest latency and
    the shortest period). When the queue is full the oldest packet is dropped (counted)."""
    c = config.condition
    if c is None:
        return config.delay_steps + 2

    def hi(name: str) -> float:
        return config.ranges[name][1] if name in config.ranges else float(getattr(c, name))

    def lo(name: str) -> float:
        return config.ranges[name][0] if name in config.ranges else float(getattr(c, name))

    period = max(config.dt, lo("update_period_s") - hi("period_jitter_s"))
    return int(math.ceil((hi("latency_s") + 4.0 * hi("latency_spread_s")) / period)) + 4


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
    c[dyn.C_WARM] = config.warmup_steps
    c[dyn.C_Q] = queue_capacity(config)
    c[dyn.C_OBSV1] = 1.0 if config.version == "v1" else 0.0
    return c


#: how the kernels compute the step's sin/cos (the ``sincos`` keyword of the envs): "simd" (the
#: default since 0.2.0: :func:`~auv_follow_env.dynamics.fast_sincos` in SIMD loops, within 1 ULP)
#: or "libm" (glibc's scalar calls: the path the v0 golden arrays were recorded with)
SINCOS = ("simd", "libm")


def check_sincos(sincos: object = None, fast_math: object = None) -> str:
    """The envs' ``sincos`` keyword resolved against its former name ``fast_math``, or a ValueError
    naming the argument.

    ``sincos``: None (the default, "simd"), "simd" or "libm". ``fast_math`` (former name, kept
    working): None (not given), True (= "simd") or False (= "libm"); given with a ``sincos`` that
    says otherwise, it is an error.
    """
    if sincos is not None and (not isinstance(sincos, str) or sincos not in SINCOS):
        raise ValueError(f"sincos={sincos!r} is invalid: pass 'simd' (the default: SIMD polynomial sin/cos) or "
                         f"'libm' (glibc's scalar sin/cos)")
    if fast_math is None:
        return "simd" if sincos is None else sincos
    if not isinstance(fast_math, (bool, np.bool_)):
        raise ValueError(f"fast_math={fast_math!r} is invalid: fast_math is the former name of sincos; pass True "
                         f"(sincos='simd', the default) or False (sincos='libm'), or use sincos")
    implied = "simd" if fast_math else "libm"
    if sincos is not None and sincos != implied:
        raise ValueError(f"fast_math={bool(fast_math)} contradicts sincos={sincos!r}: fast_math=True means "
                         f"sincos='simd' and fast_math=False sincos='libm'; pass only sincos")
    return implied


def _aligned_zeros(rows: int, cols: int) -> np.ndarray:
    """A zero (rows, cols) float64 array whose rows start on 64-byte cache lines where cols is a
    multiple of 8 (so each 8-sample write of the error history fills exactly one line)."""
    buf = np.zeros(rows * cols + 8)
    off = (-buf.ctypes.data % 64) // 8
    return buf[off:off + rows * cols].reshape(rows, cols)


class BatchSim:
    """N independent AUVFollow episodes stepped together by the numba kernels.

    ``sincos="simd"`` (default) computes the sin/cos of each step (the ten tones at the new step,
    both headings, the observation's relative heading) with
    :func:`~auv_follow_env.dynamics.fast_sincos` in SIMD loops; ``"libm"`` with glibc's scalar
    calls. Within 1 ULP of each other, not bit-identical (see the env docs).

    ``draw_ahead`` (v1; the vector env): draw each env's next episode ahead, several envs per
    call (:class:`_Episodes`; the same episodes in the same order, but the generators passed
    to :meth:`reset` advance before the episode starts: only for generators nobody else uses).
    """

    def __init__(self, config: EnvConfig, num_envs: int, sincos: str = "simd", *, packed: bool = False,
                 draw_ahead: bool = False) -> None:
        self.config = config
        self.num_envs = num_envs
        self.sincos = check_sincos(sincos)
        cfg = config_vector(config)
        cfg[dyn.C_FAST] = 1.0 if self.sincos == "simd" else 0.0
        self.v1 = config.version == "v1"
        q = int(cfg[dyn.C_Q])
        obs_dim = OBS_DIM_V1 if self.v1 else OBS_DIM
        #: packed (one env only): every array below is a view of this one buffer, for
        #: :func:`~auv_follow_env.kernel_one.step_one` (see :meth:`step_one_call`); else None
        self.buf: np.ndarray | None = None
        if packed:
            if num_envs != 1:
                raise ValueError(f"packed=True is for one env, not {num_envs}")
            self.buf, arrays = packed_arrays(q, obs_dim, config.n_steps)
            for name, arr in arrays.items():
                setattr(self, name, arr)
            self.cfg[:] = cfg
        else:
            self.cfg = cfg
            self.state = np.zeros((num_envs, 9))
            self.k = np.zeros(num_envs, dtype=np.int64)
            self.proc = np.zeros((num_envs, dyn.NR))
            self.queue = np.zeros((num_envs, q, dyn.NQ))
            self.rs = np.zeros(num_envs, dtype=np.uint64)
            self.params = np.zeros((num_envs, dyn.NP))
            self.obs = np.zeros((num_envs, obs_dim), dtype=np.float32)
            self.truth = np.zeros((num_envs, dyn.NT))
            self.err_hist = _aligned_zeros(num_envs, config.n_steps)  # env x sample (dynamics.step_range)
            self.err_stage = np.zeros((num_envs, 8))  # the latest samples, 8 per env
            self.rew = np.zeros(num_envs)
            self.term = np.zeros(num_envs, dtype=np.bool_)
        #: v1: the envs' episode draws and conditions (a vector env's next episodes drawn ahead)
        self._episodes = _Episodes(self, ahead=draw_ahead)
        self.sample_times = config.dt * np.arange(1, config.n_steps + 1)

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator], *, auto: bool = False) -> None:
        """New episodes for envs ``idx``, drawing env idx[j]'s parameters from rngs[j]. ``auto``: an
        autoreset (with ``draw_ahead``, these envs' next episodes are then started ahead)."""
        idx = np.asarray(idx, dtype=np.int64)
        if len(rngs) != len(idx):
            raise ValueError(f"{len(idx)} envs to reset but {len(rngs)} generators")
        if len(idx):
            self._episodes.start(idx, rngs, auto)

    def reset_on_threads(self, chunks: int) -> None:
        """Run resets of two blocks of envs or more, and the starts made ahead, on numba's threads
        (:func:`~auv_follow_env.dynamics.reset_kernel_parallel`, ``chunks`` slices; the same results)."""
        self._episodes.kernel = (dyn.reset_kernel_parallel, (chunks,))

    def condition(self, i: int) -> dict[str, object]:
        """v1: env i's condition of its present episode (every field, with the drawn values)."""
        if self._episodes.cond is None:
            raise ValueError("condition() needs a v1 sim after its first reset")
        return self._episodes.condition(i)

    def conditions(self, mask: np.ndarray) -> dict[str, np.ndarray]:
        """v1: the conditions of the envs in ``mask`` by field, (N,) arrays (NaN / None elsewhere)."""
        if self._episodes.cond is None:
            raise ValueError("conditions() needs a v1 sim after its first reset")
        return self._episodes.conditions(mask)

    def step(self, action_flat: np.ndarray) -> int:
        """Advance all envs; returns -1 or the index of an env with a non-finite action."""
        kernel, args = self.step_call()
        return kernel(*args, action_flat)

    def step_call(self) -> tuple:
        """(kernel, leading args) so a hot loop can call ``kernel(*args, action_flat)``."""
        return dyn.step_kernel, tuple(getattr(self, name) for name in STEP_ARRAYS)

    def step_one_call(self) -> tuple:
        """(kernel, buffer) of a packed sim: ``kernel(buffer, action)`` is one step, returning
        (bad, reward, terminated, k, tracking error) (:func:`~auv_follow_env.kernel_one.step_one`)."""
        if self.buf is None:
            raise ValueError("step_one_call needs a BatchSim made with packed=True")
        return step_one, self.buf

    def link_stats(self, i: int) -> dict[str, int]:
        """Env i's packet counts since t = 0: sent, lost, arrived (accepted), discarded
        (arrived after a newer one), overflow (dropped from a full queue)."""
        p = self.proc[i]
        return {key: int(p[col]) for key, col in LINK_COUNTERS.items()}

    def errors(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(errors, times) recorded so far in env i's episode (post-step samples)."""
        n = min(int(self.k[i]), self.config.n_steps)
        return dyn.error_samples(self.err_hist, self.err_stage, i, n), self.sample_times[:n]
