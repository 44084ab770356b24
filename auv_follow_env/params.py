"""Parameters of the plant and the task as frozen values.

Every number here that the paper does not give is *our choice*; the comment beside it
says so and gives its unit. Presets (scenarios S1-S4, disturbance levels L0-L2) are
written once, here; variants are made with :func:`dataclasses.replace` or through the
environment's keyword overrides, which build a validated :class:`EnvConfig`.

Sources: Zhang et al., J. Mar. Sci. Eng. 2026, 14(11), 963, Tables 2-3 and eq. (63);
``docs/paper_notes.md`` for the restored signs and suggested values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType

import numpy as np

__all__ = [
    "VehicleParams",
    "TargetParams",
    "DisturbanceLevel",
    "Scenario",
    "EnvConfig",
    "TaskSpec",
    "SCENARIOS",
    "DISTURBANCE_LEVELS",
    "NOMINAL_VEHICLE",
    "make_config",
    "make_task_spec",
    "UnknownKeywordError",
]


class UnknownKeywordError(TypeError, ValueError):
    """A keyword that the env (or :func:`make_config`) does not take.

    A ``TypeError``, as Python raises for an unexpected keyword argument (tools such as
    TorchRL's ``GymEnv`` drop a keyword they tried when they see one), and also a
    ``ValueError``, so callers that catch the bad-value errors of the overrides catch it too.
    The message names every unknown keyword ("unexpected keyword argument 'name'") and lists
    the valid ones.
    """


def _require(cond: bool, name: str, value: object, allowed: str) -> None:
    if not cond:
        raise ValueError(f"{name}={_short(value)} is invalid: must be {allowed}")


def _is_real(v: object) -> bool:
    """A real number: int, float or a numpy integer/floating scalar, not a bool."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _float_or_nan(v: object) -> float:
    """A real number as a float; NaN for anything else, and for an int too large for a float
    (10**400), so that every range check refuses it with the field's own message."""
    if not _is_real(v):
        return math.nan
    try:
        return float(v)  # type: ignore[arg-type]
    except OverflowError:
        return math.nan


def _too_large(v: object) -> bool:
    """An int too large for a float (only Python ints can be: numpy's fit in a float64)."""
    if not isinstance(v, int) or isinstance(v, bool):
        return False
    try:
        float(v)
    except OverflowError:
        return True
    return False


def _finite_real(v: object) -> bool:
    """A real number (not a bool) that is finite as a float."""
    return math.isfinite(_float_or_nan(v))


def _short(v: object) -> str:
    """``repr(v)``, cut to 80 characters (an int with 400 digits is named, not printed)."""
    r = repr(v)
    return r if len(r) <= 80 else f"{r[:60]}...({len(r)} characters)"


def as_real(name: str, v: object) -> float:
    """``v`` as a float, or a ValueError naming ``name`` (strings, bools, None are refused, and
    ints too large for a float)."""
    if not _is_real(v):
        raise ValueError(f"{name}={_short(v)} is invalid: must be a real number (got {type(v).__name__})")
    try:
        return float(v)  # type: ignore[arg-type]
    except OverflowError:
        raise ValueError(f"{name}={_short(v)} is invalid: must be a finite real number (this integer is too "
                         f"large for a float)") from None


def as_real_tuple(name: str, v: object, n: int) -> tuple[float, ...]:
    """``v`` (tuple, list or 1-D ndarray of ``n`` real numbers) as a tuple of floats."""
    if isinstance(v, np.ndarray):
        v = v.tolist() if v.ndim == 1 else v
    if isinstance(v, (str, bytes, dict, set)) or not isinstance(v, (tuple, list)) or len(v) != n \
            or not all(_is_real(x) for x in v):
        raise ValueError(f"{name}={_short(v)} is invalid: must be a sequence (tuple, list or array) of {n} "
                         f"real numbers")
    if any(_too_large(x) for x in v):
        raise ValueError(f"{name}={_short(v)} is invalid: must be {n} finite real numbers (an integer is too "
                         f"large for a float)")
    return tuple(float(x) for x in v)


def _in_range(name: str, v: float, lo: float, hi: float, unit: str = "", lo_open: bool = False) -> None:
    ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:
        raise ValueError(f"{name}={_short(v)} is invalid: must be a finite number in "
                         f"{'(' if lo_open else '['}{lo:g}, {hi:g}]{' ' + unit if unit else ''}")


def _finite_positive(obj: object, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _require(_finite_real(v) and v > 0, n, v, "a finite number > 0")


def _finite_nonneg(obj: object, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _require(_finite_real(v) and v >= 0, n, v, "a finite number >= 0")


def _real_seq(v: object, n: int) -> bool:
    """``v`` is a tuple or list of ``n`` finite real numbers."""
    return isinstance(v, (tuple, list)) and len(v) == n and all(_finite_real(x) for x in v)


@dataclass(frozen=True, kw_only=True)
class VehicleParams:
    """Planar 3-DOF vehicle, eqs. (6)-(8). The paper gives no values; these are ours.

    A small ROV with added mass included; linear damping stands in for quadratic drag
    near 0.5 m/s (docs/paper_notes.md, suggested values).
    """

    m: float = 25.0  #: equivalent mass incl. added mass [kg] (our choice)
    I_z: float = 2.0  #: yaw moment of inertia incl. added inertia [kg m^2] (our choice)
    X_u: float = 15.0  #: surge linear damping [N s/m] (our choice)
    Y_v: float = 20.0  #: sway linear damping [N s/m] (our choice)
    N_r: float = 3.0  #: yaw linear damping [N m s/rad] (our choice)

    def __post_init__(self) -> None:
        _finite_positive(self, "m", "I_z", "X_u", "Y_v", "N_r")

    def with_mismatch(self, mismatch: float) -> "VehicleParams":
        """The true plant: damping = nominal * (1 + mismatch); inertia unchanged."""
        k = 1.0 + mismatch
        return VehicleParams(m=self.m, I_z=self.I_z, X_u=self.X_u * k, Y_v=self.Y_v * k,
                             N_r=self.N_r * k)


NOMINAL_VEHICLE = VehicleParams()


@dataclass(frozen=True, kw_only=True)
class TargetParams:
    """Manoeuvring target, eq. (10): u_t = v_bar (1 + a_u sin(2 pi t / P_u + phi_u)),
    v_t = 0, r_t = a_r sin(2 pi t / P_r + phi_r). Phases are drawn from the env's seed.

    ``speed`` is Table 2's mean speed; the manoeuvre amplitudes and periods are ours
    (docs/paper_notes.md, suggested values), rising from S1 to S4.
    """

    speed: float  #: mean surge speed v_bar [m/s] (Table 2)
    surge_amp: float  #: relative surge-speed modulation a_u [-] (our choice)
    surge_period: float  #: period of the speed change P_u [s] (our choice)
    yaw_rate_amp: float  #: yaw-rate amplitude a_r [rad/s] (our choice)
    yaw_period: float  #: period of the turns P_r [s] (our choice)

    def __post_init__(self) -> None:
        _finite_positive(self, "speed", "surge_period", "yaw_period")
        _finite_nonneg(self, "yaw_rate_amp")
        _require(_finite_real(self.surge_amp) and 0 <= self.surge_amp < 1,
                 "surge_amp", self.surge_amp, "a number in [0, 1)")


@dataclass(frozen=True, kw_only=True)
class DisturbanceLevel:
    """Table 3: current ranges (inertial x/y components of v_c^I) and peaks of the lumped
    disturbances (d_u, d_v, d_r).

    The peaks are read per unit mass (our reading; docs/paper_notes.md): the plant receives the
    forces m d_u, m d_v [N] and the moment I_z d_r [N m]. Each disturbance is two tones
    (0.35 and 0.9 rad/s, weights 0.6 and 0.4, random phases), so |d| <= peak. Each current
    component is a sinusoid spanning exactly [min, max], period drawn in [40, 80] s.
    """

    name: str
    current_x: tuple[float, float]  #: inertial-x current range [m/s] (Table 3 "surge")
    current_y: tuple[float, float]  #: inertial-y current range [m/s] (Table 3 "sway")
    peaks: tuple[float, float, float]  #: (d_u, d_v, d_r) peaks [m/s^2, m/s^2, rad/s^2]
    description: str = ""

    def __post_init__(self) -> None:
        for n in ("current_x", "current_y"):
            r = getattr(self, n)
            _require(_real_seq(r, 2) and r[0] <= r[1], n, r, "a finite (min, max) with min <= max")
        _require(_real_seq(self.peaks, 3) and all(p >= 0 for p in self.peaks),
                 "peaks", self.peaks, "three finite numbers >= 0")


# Table 3, signs restored as in docs/paper_notes.md (sway ranges were printed out of order).
DISTURBANCE_LEVELS: Mapping[str, DisturbanceLevel] = MappingProxyType({
    "L0": DisturbanceLevel(name="L0", current_x=(0.0, 0.0), current_y=(0.0, 0.0),
                           peaks=(0.0, 0.0, 0.0), description="no disturbance"),
    "L1": DisturbanceLevel(name="L1", current_x=(0.01, 0.03), current_y=(-0.018, 0.002),
                           peaks=(0.02, 0.015, 0.008), description="mild"),
    "L2": DisturbanceLevel(name="L2", current_x=(0.02, 0.10), current_y=(-0.065, 0.01),
                           peaks=(0.08, 0.065, 0.028), description="strong"),
})


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """One row of Table 2 plus what the paper leaves open (target manoeuvres, mismatch)."""

    name: str
    target: TargetParams
    delay_s: float  #: target-state delay tau [s] (Table 2)
    disturbance: str  #: default disturbance level (Table 2)
    mismatch: float  #: true damping = nominal * (1 + mismatch) [-] (our choice, docs/paper_notes.md)
    description: str = ""


SCENARIOS: Mapping[str, Scenario] = MappingProxyType({
    "S1": Scenario(
        name="S1", delay_s=0.5, disturbance="L0", mismatch=0.15,
        target=TargetParams(speed=0.45, surge_amp=0.025, surge_period=30.0,
                            yaw_rate_amp=0.02, yaw_period=40.0),
        description="baseline: delay only, weak manoeuvres, negligible disturbance"),
    "S2": Scenario(
        name="S2", delay_s=1.0, disturbance="L1", mismatch=0.60,
        target=TargetParams(speed=0.49, surge_amp=0.075, surge_period=20.0,
                            yaw_rate_amp=0.05, yaw_period=30.0),
        description="delayed tracking: larger delay, noticeable manoeuvres, mild current"),
    "S3": Scenario(
        name="S3", delay_s=1.5, disturbance="L2", mismatch=0.60,
        target=TargetParams(speed=0.49, surge_amp=0.075, surge_period=20.0,
                            yaw_rate_amp=0.05, yaw_period=30.0),
        description="robust tracking: large delay, strong current and disturbance"),
    "S4": Scenario(
        name="S4", delay_s=2.0, disturbance="L2", mismatch=1.05,
        target=TargetParams(speed=0.52, surge_amp=0.10, surge_period=15.0,
                            yaw_rate_amp=0.07, yaw_period=24.0),
        description="integrated hard case: largest delay, strongest manoeuvres, severe mismatch"),
})

#: p_d, eq. (63), surge sign restored (the reference lies behind the target) [m]
OFFSET_P_D: tuple[float, float] = (-0.65, 0.12)


#: bounds enforced on the task's numbers (ours): they keep the RK4 stable, the arrays small
#: and the metrics defined; a value outside gets a ValueError naming the field and the range
BOUNDS: Mapping[str, tuple[float, float, str]] = MappingProxyType({
    "dt": (1e-3, 0.2, "s"),
    "episode_s": (0.0, 3600.0, "s"),
    "delay_s": (0.0, 30.0, "s"),
    "steady_start_s": (0.0, 3600.0, "s"),
    "mismatch": (-0.9, 10.0, "-"),
    "init_offset_m": (0.0, 100.0, "m"),
    "max_distance_m": (0.0, 1e4, "m"),
    "effort_weight": (0.0, 1e3, "-"),
    "psi_d": (-2 * math.pi, 2 * math.pi, "rad"),
})
MAX_SUBSTEPS = 100  #: physics_substeps in [1, MAX_SUBSTEPS]
MAX_STEPS = 200_000  #: episode_s / dt at most this many control steps
MAX_FORCE = 1e5  #: force limits in (0, MAX_FORCE] [N, N, N m]
#: |h lambda| bound of the RK4 integrator's stability check (its region contains the left
#: half-disk of radius 2.61; 2.5 keeps a margin)
RK4_RADIUS = 2.5
MAX_OFFSET = 100.0  #: |p_d| components at most this [m]


@dataclass(frozen=True, kw_only=True)
class EnvConfig:
    """Everything that defines one AUVFollow task. Built by :func:`make_config`.

    Attributes are documented with units; values marked "ours" are our choices. Every
    number is bounded (:data:`BOUNDS`); ``condition`` is None for the v0 ids and the
    acoustic-link :class:`Condition` (with ``ranges`` drawn per reset) for the v1 ids.
    """

    scenario: Scenario
    disturbance: DisturbanceLevel
    delay_s: float  #: target-state delay tau [s]; a multiple of ``dt`` (v0)
    mismatch: float  #: true damping = nominal * (1 + mismatch) [-]; > -1
    nominal: VehicleParams = NOMINAL_VEHICLE  #: what controllers are told
    dt: float = 0.05  #: control step [s] (ours: 20 Hz)
    physics_substeps: int = 2
    """RK4 substeps per control step (ours: 0.025 s; measured over a 60 s S4 run, the pose
    differs from a 40-substep solution by < 1e-7 m, so the physics is converged)."""
    episode_s: float = 60.0  #: episode length [s] (ours, docs/paper_notes.md)
    steady_start_s: float = 10.0  #: start of the steady-state window [s] (paper, Sec. 4.3)
    p_d: tuple[float, float] = OFFSET_P_D  #: reference offset in the target body frame [m]
    psi_d: float = 0.0  #: heading offset [rad] (ours: the paper gives none)
    force_limits: tuple[float, float, float] = (150.0, 150.0, 30.0)
    """(F_u [N], F_v [N], F_r [N m]) reached at action +-1 (ours)."""
    init_offset_m: float = 0.87
    """The follower starts at rest this far behind the delayed reference point, along the
    target's delayed heading [m] (ours; the paper's full-run maxima are 0.83-0.89 m)."""
    max_distance_m: float = 20.0
    """Terminate when the follower is further than this from the true reference [m] (ours)."""
    effort_weight: float = 0.0
    """Reward = -error - effort_weight * mean(action^2) (ours: 0 by default)."""
    condition: Condition | None = None
    """v1 only: the acoustic link, target, current and thruster settings (None: v0)."""
    ranges: Mapping[str, tuple[float, float]] = field(default_factory=lambda: MappingProxyType({}))
    """v1 only: condition fields drawn uniformly from (min, max) at every reset (a tier)."""
    tier: str | None = None  #: v1 only: the tier's name, if any

    def __post_init__(self) -> None:
        for name, (lo, hi, unit) in BOUNDS.items():
            _in_range(name, as_real(name, getattr(self, name)), lo, hi, unit,
                      lo_open=name in ("dt", "episode_s", "max_distance_m"))
        _require(isinstance(self.physics_substeps, (int, np.integer)) and not isinstance(self.physics_substeps, bool)
                 and 1 <= self.physics_substeps <= MAX_SUBSTEPS, "physics_substeps", self.physics_substeps,
                 f"an integer in [1, {MAX_SUBSTEPS}]")
        steps = self.delay_s / self.dt
        _require(abs(steps - round(steps)) < 1e-9 * max(1.0, steps), "delay_s", self.delay_s,
                 f"a multiple of dt={self.dt} s (the delay line holds whole control steps)")
        n = self.episode_s / self.dt
        _require(abs(n - round(n)) < 1e-9 * max(1.0, n) and 1 <= round(n) <= MAX_STEPS, "episode_s",
                 self.episode_s, f"a positive multiple of dt={self.dt} s with at most {MAX_STEPS} steps")
        _require(self.steady_start_s < self.episode_s, "steady_start_s", self.steady_start_s,
                 f"less than episode_s={self.episode_s} s (else the steady-state window is empty)")
        _require(_real_seq(self.force_limits, 3) and all(0 < f <= MAX_FORCE for f in self.force_limits),
                 "force_limits", self.force_limits, f"three finite numbers in (0, {MAX_FORCE:g}] [N, N, N m]")
        _require(_real_seq(self.p_d, 2) and all(abs(v) <= MAX_OFFSET for v in self.p_d), "p_d",
                 self.p_d, f"two finite numbers in [-{MAX_OFFSET:g}, {MAX_OFFSET:g}] m")
        _require(isinstance(self.nominal, VehicleParams), "nominal", self.nominal, "a VehicleParams")
        # RK4 stability: h * (fastest damping rate) well inside RK4's real-axis limit 2.78
        worst = 1.0 + max(self.mismatch, self.ranges.get("mismatch", (0.0, self.mismatch))[1])
        v = self.nominal
        rate = worst * max(v.X_u / v.m, v.Y_v / v.m, v.N_r / v.I_z)
        h = self.dt / self.physics_substeps
        _require(h * rate <= 1.0, "physics_substeps", self.physics_substeps,
                 f"large enough that dt / physics_substeps * (fastest damping rate {rate:.3g} 1/s) <= 1 "
                 f"(now {h * rate:.3g}); lower dt={self.dt} or the mismatch, or raise physics_substeps")
        # yaw coupling: the surge/sway block has eigenvalues -damping +- i r, and |r| can reach
        # F_r / N_r (true, least damped); RK4 is stable for |h lambda| <= 2.61 in the left half-plane
        least = 1.0 + min(self.mismatch, self.ranges.get("mismatch", (self.mismatch, 0.0))[0])
        r_max = self.force_limits[2] / (v.N_r * least)
        z = h * math.hypot(rate, r_max)
        if z > RK4_RADIUS:
            need = math.ceil(self.dt * math.hypot(rate, r_max) / RK4_RADIUS)
            raise ValueError(
                f"force_limits={tuple(self.force_limits)!r} is invalid with physics_substeps={self.physics_substeps} "
                f"and dt={self.dt} s: the yaw rate can reach F_r / N_r = {r_max:.3g} rad/s and the integrator "
                f"needs dt / physics_substeps * {math.hypot(rate, r_max):.3g} 1/s <= {RK4_RADIUS} (now {z:.3g}); "
                f"lower F_r or raise physics_substeps to >= {need}"
                + ("" if need <= MAX_SUBSTEPS else f" (more than the maximum {MAX_SUBSTEPS}: lower F_r or dt)"))

    @property
    def version(self) -> str:
        """"v0" (the paper's constant delay, 16 fields) or "v1" (the acoustic link, 20 fields)."""
        return "v0" if self.condition is None else "v1"

    @property
    def delay_steps(self) -> int:
        """tau / dt."""
        return int(round(self.delay_s / self.dt))

    @property
    def n_steps(self) -> int:
        """Control steps per episode (episode_s / dt)."""
        return int(round(self.episode_s / self.dt))

    @property
    def true_vehicle(self) -> VehicleParams:
        """The simulated plant: nominal inertia, damping scaled by (1 + mismatch)."""
        return self.nominal.with_mismatch(self.mismatch)

    @property
    def warmup_steps(self) -> int:
        """Control steps simulated before t = 0 to fill the link (v0: tau / dt)."""
        if self.condition is None:
            return self.delay_steps
        return int(math.ceil(self.condition.warmup_s / self.dt - 1e-9))

    def task_spec(self) -> "TaskSpec":
        c = self.condition
        delay = self.delay_s if c is None else c.latency_s
        if c is not None and "latency_s" in self.ranges:
            delay = 0.5 * sum(self.ranges["latency_s"])
        return TaskSpec(
            scenario=self.scenario.name, disturbance=self.disturbance.name, dt=self.dt,
            delay_s=delay, delay_steps=int(round(delay / self.dt)), p_d=self.p_d, psi_d=self.psi_d,
            nominal=self.nominal, force_limits=self.force_limits, episode_s=self.episode_s,
            n_steps=self.n_steps, steady_start_s=self.steady_start_s, layout=self.version, tier=self.tier,
            **({} if c is None else {"thruster_tc_s": c.thruster_tc_s, "thruster_rate": c.thruster_rate}))


@dataclass(frozen=True, kw_only=True)
class TaskSpec:
    """The static facts a controller may use besides the observation.

    A real follower knows these (its delay, its desired offset, its own nominal model, its
    control rate); it does not know the true damping, the current's future or the target's
    present state. Exposed as ``env.unwrapped.task_spec`` and by :func:`make_task_spec`.
    On the v1 ids ``delay_s`` is only the nominal latency (the middle of the tier's range):
    the observed ``packet_age`` says how old each packet really is.
    """

    scenario: str
    disturbance: str
    dt: float  #: control step [s]
    delay_s: float  #: tau [s] (v1: nominal latency)
    delay_steps: int  #: tau / dt
    p_d: tuple[float, float]  #: reference offset in the target body frame [m]
    psi_d: float  #: heading offset [rad]
    nominal: VehicleParams  #: nominal m, I_z, X_u, Y_v, N_r given to the controllers
    force_limits: tuple[float, float, float]  #: action +-1 <-> (F_u, F_v, F_r) [N, N, N m]
    episode_s: float  #: episode length [s]
    n_steps: int  #: control steps per episode
    steady_start_s: float  #: start of the steady-state metric window [s]
    layout: str = "v0"  #: observation layout: "v0" (16 fields) or "v1" (20 fields)
    tier: str | None = None  #: v1 tier name, if any
    thruster_tc_s: float = 0.0
    """v1 only: the thrusters' first-order lag time constant [s] (0: none; v0 has none). A
    follower knows its own thrusters; if a task draws it per reset, this is the middle of the
    range (as ``delay_s``)."""
    thruster_rate: float = math.inf
    """v1 only: the thrusters' rate limit, fraction of the force limit per second (inf: none;
    v0 has none); the middle of the range if a task draws it per reset."""

    @property
    def obs_dim(self) -> int:
        """Width of the observations of this task (16 for v0, 20 for v1)."""
        return 16 if self.layout == "v0" else 20


# --- v1: the acoustic link, an unpredictable target, a wandering current --------------------

LATENCY_MODELS: tuple[str, ...] = ("constant", "uniform", "gauss_markov")


@dataclass(frozen=True)
class ConditionField:
    """One v1 condition parameter: default, allowed closed range, unit and meaning."""

    name: str
    default: float | None
    lo: float
    hi: float
    unit: str
    doc: str
    lo_open: bool = False


#: the scalar v1 parameters, in documentation order (every one overridable through gym.make,
#: and every one can be drawn per reset by a tier)
CONDITION_FIELDS: tuple[ConditionField, ...] = (
    # link: packets, latency, loss
    ConditionField("update_period_s", None, 0.0, 60.0, "s",
                   "send period of the target's state (None: every control step)", lo_open=True),
    ConditionField("period_jitter_s", 0.0, 0.0, 60.0, "s",
                   "each send interval is period + U(-jitter, +jitter) (jitter < period)"),
    ConditionField("latency_s", None, 0.0, 30.0, "s", "mean latency of a packet (None: delay_s)"),
    ConditionField("latency_spread_s", 0.0, 0.0, 30.0, "s",
                   "uniform: half-width; gauss_markov: standard deviation (latency clipped at 0)"),
    ConditionField("latency_corr_s", 10.0, 0.0, 1e4, "s", "correlation time of the Gauss-Markov latency",
                   lo_open=True),
    ConditionField("loss_prob", 0.0, 0.0, 1.0, "-", "i.i.d. probability that a packet is lost"),
    ConditionField("burst_p_good_bad", 0.0, 0.0, 1.0, "-",
                   "Gilbert-Elliott: probability per packet of going from the good to the bad state "
                   "(0: no bursts)"),
    ConditionField("burst_p_bad_good", 1.0, 0.0, 1.0, "-",
                   "Gilbert-Elliott: probability per packet of leaving the bad state (mean bad run "
                   "1 / p packets)", lo_open=True),
    ConditionField("burst_loss_bad", 1.0, 0.0, 1.0, "-", "loss probability in the bad state"),
    # fix noise
    ConditionField("fix_sigma_m", 0.0, 0.0, 100.0, "m", "position-fix noise sigma at zero range"),
    ConditionField("fix_sigma_per_m", 0.0, 0.0, 1.0, "m/m",
                   "growth of the position sigma with range (sigma = fix_sigma_m + k * range, as a USBL)"),
    ConditionField("heading_sigma_rad", 0.0, 0.0, math.pi, "rad", "heading-fix noise sigma"),
    ConditionField("velocity_sigma_mps", 0.0, 0.0, 10.0, "m/s", "noise sigma on the reported u_t and v_t"),
    ConditionField("yaw_rate_sigma_radps", 0.0, 0.0, 10.0, "rad/s", "noise sigma on the reported r_t"),
    # target
    ConditionField("target_speed", None, 0.0, 5.0, "m/s", "mean surge speed v_bar (None: the scenario's)"),
    ConditionField("target_surge_amp", None, 0.0, 0.99, "-", "relative surge tone amplitude a_u "
                   "(None: the scenario's)"),
    ConditionField("target_yaw_rate_amp", None, 0.0, 1.0, "rad/s", "yaw-rate tone amplitude a_r "
                   "(None: the scenario's)"),
    ConditionField("target_speed_std", 0.0, 0.0, 2.0, "m/s",
                   "std of the OU deviation of the target's surge speed"),
    ConditionField("target_speed_corr_s", 20.0, 0.0, 1e4, "s", "its correlation time", lo_open=True),
    ConditionField("target_yaw_rate_std", 0.0, 0.0, 1.0, "rad/s", "std of the OU deviation of the yaw rate"),
    ConditionField("target_yaw_rate_corr_s", 10.0, 0.0, 1e4, "s", "its correlation time", lo_open=True),
    ConditionField("target_speed_min", 0.0, 0.0, 5.0, "m/s", "surge speed is clipped to [min, max]"),
    ConditionField("target_speed_max", 2.0, 0.0, 5.0, "m/s", "upper surge-speed bound", lo_open=True),
    ConditionField("target_yaw_rate_max", 0.5, 0.0, 5.0, "rad/s", "|r_t| is clipped to this", lo_open=True),
    # leader targets: hidden manoeuvre modes instead of the OU deviations (docs/tiers.md, "Leader tiers")
    ConditionField("leader_modes", 0.0, 0.0, 2.0, "-",
                   "0: the target above (tones + OU); 1: a leader with cruise and turn modes; 2: also loiter "
                   "and sprint"),
    ConditionField("leader_survey_share", 0.0, 0.0, 1.0, "-",
                   "share of a leader's episodes that are surveys (legs and U-turns) instead of wandering"),
    ConditionField("leader_cruise_speed", 0.5, 0.0, 5.0, "m/s", "speed commanded in cruise, turns and survey legs",
                   lo_open=True),
    ConditionField("leader_turn_rate", 0.15, 0.0, 2.0, "rad/s", "turn rate of a wandering turn"),
    ConditionField("leader_cruise_mean_s", 10.0, 0.0, 1e4, "s", "mean duration of cruise (Gamma(4) durations)",
                   lo_open=True),
    ConditionField("leader_turn_mean_s", 6.0, 0.0, 1e4, "s", "mean duration of a turn", lo_open=True),
    ConditionField("leader_loiter_speed", 0.1, 0.0, 5.0, "m/s", "speed commanded while loitering"),
    ConditionField("leader_loiter_mean_s", 8.0, 0.0, 1e4, "s", "mean duration of a loiter", lo_open=True),
    ConditionField("leader_sprint_speed", 0.9, 0.0, 5.0, "m/s", "speed commanded in a sprint"),
    ConditionField("leader_sprint_mean_s", 5.0, 0.0, 1e4, "s", "mean duration of a sprint", lo_open=True),
    ConditionField("leader_leg_m", 10.0, 0.0, 1e4, "m", "survey leg length (each leg within +- 5 %)",
                   lo_open=True),
    ConditionField("leader_uturn_rate", 0.25, 0.0, 2.0, "rad/s", "turn rate of a survey's U-turn", lo_open=True),
    ConditionField("leader_speed_lag_s", 2.0, 0.0, 1e3, "s", "time constant of the speed's first-order lag",
                   lo_open=True),
    ConditionField("leader_rate_lag_s", 1.0, 0.0, 1e3, "s", "time constant of the turn rate's lag", lo_open=True),
    ConditionField("leader_wobble_speed", 0.02, 0.0, 1.0, "m/s", "std of the OU wobble on the leader's speed"),
    ConditionField("leader_wobble_rate", 0.01, 0.0, 1.0, "rad/s", "std of the OU wobble on its turn rate"),
    ConditionField("leader_wobble_corr_s", 5.0, 0.0, 1e4, "s", "the wobbles' correlation time", lo_open=True),
    ConditionField("outlier_share", 0.0, 0.0, 1.0, "-",
                   "share of position fixes that are multipath outliers (a 2-D Student-t error, 3 dof)"),
    ConditionField("outlier_scale_m", 1.0, 0.0, 100.0, "m", "scale of the outliers' Student-t error"),
    # current
    ConditionField("current_speed", 0.0, 0.0, 3.0, "m/s",
                   "mean speed of the Gauss-Markov current (added to the level's tones)"),
    ConditionField("current_speed_std", 0.0, 0.0, 3.0, "m/s", "std of its speed (speed clipped at 0)"),
    ConditionField("current_corr_s", 60.0, 0.0, 1e5, "s", "correlation time of its speed", lo_open=True),
    ConditionField("current_direction_rad", None, -2 * math.pi, 2 * math.pi, "rad",
                   "its initial direction (inertial; None: drawn uniformly)"),
    ConditionField("current_direction_drift", 0.0, 0.0, 1.0, "rad/sqrt(s)",
                   "random-walk intensity of its direction"),
    # disturbances, thrusters, start
    ConditionField("disturbance_noise_u", 0.0, 0.0, 10.0, "m/s^2",
                   "std of a coloured (Gauss-Markov) surge disturbance per unit mass"),
    ConditionField("disturbance_noise_v", 0.0, 0.0, 10.0, "m/s^2", "the same in sway"),
    ConditionField("disturbance_noise_r", 0.0, 0.0, 10.0, "rad/s^2", "the same in yaw, per unit inertia"),
    ConditionField("disturbance_corr_s", 5.0, 0.0, 1e4, "s", "their correlation time", lo_open=True),
    ConditionField("thruster_tc_s", 0.0, 0.0, 10.0, "s", "first-order thruster lag time constant (0: none)"),
    ConditionField("thruster_rate", math.inf, 0.0, math.inf, "1/s",
                   "thruster rate limit, fraction of the force limit per second (inf: none)", lo_open=True),
    ConditionField("warmup_s", None, 0.0, 120.0, "s",
                   "time the target and link run before t = 0 (None: latency + 3 spread + 2 periods)"),
)
CONDITION_INDEX = MappingProxyType({f.name: f for f in CONDITION_FIELDS})
#: v1 fields that are not numbers
CONDITION_CHOICES = MappingProxyType({"latency_model": LATENCY_MODELS})
#: v1 overrides taking (min, max) [m/s]: a custom tone current replacing the level's range
CURRENT_RANGE_FIELDS: tuple[str, ...] = ("current_x", "current_y")


@dataclass(frozen=True, kw_only=True)
class Condition:
    """The v1 settings of one episode: the link, the target's random manoeuvres, the current,
    extra disturbances and the thrusters. Every field is a plain number with a documented
    unit and range (:data:`CONDITION_FIELDS`); ``latency_model`` is one of
    :data:`LATENCY_MODELS`. The defaults are v0's behaviour (a packet every step, constant
    latency tau, no loss, no noise, no random processes). Built by :func:`make_config`,
    which fills the ``None`` defaults from the scenario.
    """

    update_period_s: float
    period_jitter_s: float = 0.0
    latency_model: str = "constant"
    latency_s: float = 0.0
    latency_spread_s: float = 0.0
    latency_corr_s: float = 10.0
    loss_prob: float = 0.0
    burst_p_good_bad: float = 0.0
    burst_p_bad_good: float = 1.0
    burst_loss_bad: float = 1.0
    fix_sigma_m: float = 0.0
    fix_sigma_per_m: float = 0.0
    heading_sigma_rad: float = 0.0
    velocity_sigma_mps: float = 0.0
    yaw_rate_sigma_radps: float = 0.0
    target_speed: float = 0.5
    target_surge_amp: float = 0.0
    target_yaw_rate_amp: float = 0.0
    target_speed_std: float = 0.0
    target_speed_corr_s: float = 20.0
    target_yaw_rate_std: float = 0.0
    target_yaw_rate_corr_s: float = 10.0
    target_speed_min: float = 0.0
    target_speed_max: float = 2.0
    target_yaw_rate_max: float = 0.5
    leader_modes: float = 0.0
    leader_survey_share: float = 0.0
    leader_cruise_speed: float = 0.5
    leader_turn_rate: float = 0.15
    leader_cruise_mean_s: float = 10.0
    leader_turn_mean_s: float = 6.0
    leader_loiter_speed: float = 0.1
    leader_loiter_mean_s: float = 8.0
    leader_sprint_speed: float = 0.9
    leader_sprint_mean_s: float = 5.0
    leader_leg_m: float = 10.0
    leader_uturn_rate: float = 0.25
    leader_speed_lag_s: float = 2.0
    leader_rate_lag_s: float = 1.0
    leader_wobble_speed: float = 0.02
    leader_wobble_rate: float = 0.01
    leader_wobble_corr_s: float = 5.0
    outlier_share: float = 0.0
    outlier_scale_m: float = 1.0
    current_speed: float = 0.0
    current_speed_std: float = 0.0
    current_corr_s: float = 60.0
    current_direction_rad: float | None = None
    current_direction_drift: float = 0.0
    disturbance_noise_u: float = 0.0
    disturbance_noise_v: float = 0.0
    disturbance_noise_r: float = 0.0
    disturbance_corr_s: float = 5.0
    thruster_tc_s: float = 0.0
    thruster_rate: float = math.inf
    warmup_s: float = 0.0
    current_x: tuple[float, float] | None = None  #: custom tone current x range (min, max) [m/s]
    current_y: tuple[float, float] | None = None  #: custom tone current y range (min, max) [m/s]

    def __post_init__(self) -> None:
        for f in CONDITION_FIELDS:
            v = getattr(self, f.name)
            if v is None and f.name == "current_direction_rad":
                continue
            if not _is_real(v):
                raise ValueError(f"{f.name}={_short(v)} is invalid: must be a real number [{f.unit}]")
            v = as_real(f.name, v)
            if f.hi == math.inf:
                _require(v > f.lo if f.lo_open else v >= f.lo, f.name, v, f"a number > {f.lo:g} [{f.unit}] or inf")
            else:
                _in_range(f.name, v, f.lo, f.hi, f.unit, f.lo_open)
        _require(self.latency_model in LATENCY_MODELS, "latency_model", self.latency_model,
                 f"one of {list(LATENCY_MODELS)}")
        _require(self.period_jitter_s < self.update_period_s, "period_jitter_s", self.period_jitter_s,
                 f"less than update_period_s={self.update_period_s} s (sends must stay in order)")
        _require(self.latency_model != "uniform" or self.latency_spread_s <= self.latency_s, "latency_spread_s",
                 self.latency_spread_s, f"<= latency_s={self.latency_s} s for the uniform model (latency >= 0)")
        _require(self.target_speed_min <= self.target_speed_max, "target_speed_min", self.target_speed_min,
                 f"<= target_speed_max={self.target_speed_max} m/s")
        _require(float(self.leader_modes).is_integer(), "leader_modes", self.leader_modes, "0, 1 or 2")
        if self.leader_modes > 0:
            for n in ("target_speed_std", "target_yaw_rate_std", "target_surge_amp", "target_yaw_rate_amp"):
                _require(getattr(self, n) == 0.0, n, getattr(self, n),
                         f"0 with leader_modes={self.leader_modes:g} (the leader's modes replace the tones and "
                         "the OU deviations)")
            fastest = max(self.leader_cruise_speed, self.leader_sprint_speed if self.leader_modes >= 2 else 0.0)
            _require(self.target_speed_max >= fastest, "target_speed_max", self.target_speed_max,
                     f">= the leader's fastest commanded speed {fastest:g} m/s")
            sharpest = max(self.leader_turn_rate, self.leader_uturn_rate if self.leader_survey_share > 0 else 0.0)
            _require(self.target_yaw_rate_max >= sharpest, "target_yaw_rate_max", self.target_yaw_rate_max,
                     f">= the leader's sharpest commanded turn rate {sharpest:g} rad/s")
            _require(self.leader_uturn_rate * self.leader_rate_lag_s < math.pi, "leader_uturn_rate",
                     self.leader_uturn_rate, f"< pi / leader_rate_lag_s = {math.pi / self.leader_rate_lag_s:g} "
                     "rad/s (a U-turn's command ends when pi - rate * lag remains)")
        for n in CURRENT_RANGE_FIELDS:
            r = getattr(self, n)
            if r is not None:
                _require(_real_seq(r, 2) and all(abs(x) <= 3.0 for x in r) and r[0] <= r[1], n, r,
                         "(min, max) with min <= max, each in [-3, 3] m/s")

    def as_dict(self) -> dict[str, object]:
        """All fields by name (what ``info["condition"]`` reports at reset)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


#: keyword overrides accepted by the v0 environments (and by make_config)
OVERRIDES: tuple[str, ...] = tuple(
    f.name for f in fields(EnvConfig)
    if f.name not in ("scenario", "disturbance", "nominal", "condition", "ranges", "tier"))
#: keyword overrides accepted by the v1 environments, besides :data:`OVERRIDES`
OVERRIDES_V1: tuple[str, ...] = (tuple(f.name for f in CONDITION_FIELDS) + tuple(CONDITION_CHOICES)
                                 + CURRENT_RANGE_FIELDS)
#: v1 condition fields that a tier may draw per reset (scalars)
RANGEABLE: tuple[str, ...] = tuple(f.name for f in CONDITION_FIELDS if f.name != "warmup_s") + ("mismatch",)


#: the named arguments of the envs besides the overrides (named in the unknown-keyword message)
ENV_ARGUMENTS: tuple[str, ...] = ("scenario", "disturbance", "render_mode", "sincos", "fast_math")
#: the vector env's own arguments besides :data:`ENV_ARGUMENTS`
VECTOR_ARGUMENTS: tuple[str, ...] = ("num_envs", "max_episode_steps", "parallel", "autoreset_mode")


def unknown_keywords(unknown: list[str], allowed: tuple[str, ...], version: str = "v1") -> UnknownKeywordError:
    """The error for keywords that are neither named arguments nor overrides (``allowed``)."""
    extra = ""
    if version == "v0" and set(unknown) & set(OVERRIDES_V1):
        extra = " (the acoustic-link parameters exist only on the v1 ids, e.g. AUVFollow-Hard-v1 or AUVFollow-v1)"
    # each name in the wording Python uses for a keyword a function does not take
    what = " and an ".join(f"unexpected keyword argument {k!r}" for k in unknown)
    return UnknownKeywordError(
        f"got an {what}{extra}: valid keywords are the overrides {list(allowed)}, the envs' arguments "
        f"{list(ENV_ARGUMENTS)} and the vector env's {list(VECTOR_ARGUMENTS)}")


def _parse_overrides(overrides: Mapping[str, object], allowed: tuple[str, ...], version: str) -> dict:
    """The overrides as checked numbers, tuples or choices; None values are left out (no override).

    Raises:
        UnknownKeywordError: a keyword not in ``allowed`` (a TypeError, and a ValueError).
        ValueError: a value of the wrong type or too large for a float.
    """
    unknown = sorted(set(overrides) - set(allowed))
    if unknown:
        raise unknown_keywords(unknown, allowed, version)
    kw: dict = {}
    for k, v in overrides.items():
        if v is None:
            continue
        if k in ("force_limits", "p_d"):
            v = as_real_tuple(k, v, 3 if k == "force_limits" else 2)
        elif k in CURRENT_RANGE_FIELDS:
            v = as_real_tuple(k, v, 2)
        elif k == "physics_substeps":
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ValueError(f"physics_substeps={_short(v)} is invalid: must be an integer in [1, {MAX_SUBSTEPS}]")
            v = int(v)
        elif k in CONDITION_CHOICES:
            if not isinstance(v, str) or v not in CONDITION_CHOICES[k]:
                raise ValueError(f"{k}={_short(v)} is invalid: must be one of {list(CONDITION_CHOICES[k])}")
        elif version == "v1" and k in RANGEABLE and isinstance(v, (tuple, list, np.ndarray)):
            lo, hi = as_real_tuple(k, v, 2)
            _require(lo <= hi, k, v, "a number or a (min, max) range with min <= max, drawn at every reset")
            v = (lo, hi)
        else:
            v = as_real(k, v)
        kw[k] = v
    return kw


def _condition_defaults(sc: Scenario, dt: float, delay_s: float) -> dict[str, float]:
    return {"update_period_s": dt, "latency_s": delay_s, "target_speed": sc.target.speed,
            "target_surge_amp": sc.target.surge_amp, "target_yaw_rate_amp": sc.target.yaw_rate_amp}


def _check_every_draw(rng_map: Mapping[str, tuple[float, float]], cond_kw: Mapping[str, object]) -> None:
    """Refuse fixed / ranged combinations under which some per-reset draw breaks a rule between
    two fields (fields are drawn independently, so the worst pair of ends must pass)."""
    def span(name: str) -> tuple[float, float]:
        if name in rng_map:
            return rng_map[name]
        v = float(cond_kw.get(name, CONDITION_INDEX[name].default))  # type: ignore[arg-type]
        return v, v

    def shown(name: str) -> str:
        return f"{name}={rng_map[name]!r} (drawn per reset)" if name in rng_map else f"{name}={span(name)[0]!r}"

    if "leader_modes" in rng_map and rng_map["leader_modes"][0] != rng_map["leader_modes"][1]:
        raise ValueError(f"leader_modes={rng_map['leader_modes']!r} is invalid: the leader's mode count is fixed per "
                         "env, 0, 1 or 2, not drawn per reset (give one of these numbers)")
    rules = [("period_jitter_s", "update_period_s", lambda a, b: a < b, "<",
              "sends must stay in order"),
             ("target_speed_min", "target_speed_max", lambda a, b: a <= b, "<=", "")]
    if cond_kw.get("latency_model", "constant") == "uniform":
        rules.append(("latency_spread_s", "latency_s", lambda a, b: a <= b, "<=",
                      "the uniform latency must stay >= 0"))
    for a, b, ok, op, why in rules:
        if a not in rng_map and b not in rng_map:
            continue  # two fixed values: Condition checks them
        worst_a, worst_b = span(a)[1], span(b)[0]
        if not ok(worst_a, worst_b):
            raise ValueError(f"{shown(a)} and {shown(b)} are invalid together: a reset can draw {a}={worst_a:g} "
                             f"and {b}={worst_b:g}, but every draw must have {a} {op} {b}"
                             + (f" ({why})" if why else "") + ": narrow the ranges so that they cannot overlap")
    modes = span("leader_modes")[1]
    if modes > 0:
        _check_leader_draws(rng_map, span, shown, modes)


def _check_leader_draws(rng_map, span, shown, modes: float) -> None:
    """The Leader rules of :class:`Condition` for the worst draw of the ranges (each field is drawn
    on its own, so the bound's lowest draw must clear the highest commanded value)."""
    def refuse(bound: str, worst: float, what: str, names: tuple[str, ...]) -> None:
        ranged = [n for n in (bound, *names) if n in rng_map]
        if not ranged:
            return  # fixed values only: Condition checks them
        raise ValueError(f"{', '.join(shown(n) for n in (bound, *names))} are invalid together: a reset can draw "
                         f"{bound}={span(bound)[0]:g} below {what} {worst:g}: every draw must have {bound} >= "
                         f"{what}; narrow the ranges so that they cannot overlap")

    speeds = ("leader_cruise_speed",) + (("leader_sprint_speed",) if modes >= 2 else ())
    fastest = max(span(n)[1] for n in speeds)
    if span("target_speed_max")[0] < fastest:
        refuse("target_speed_max", fastest, "the leader's fastest commanded speed", speeds)
    rates = ("leader_turn_rate",) + (("leader_uturn_rate",) if span("leader_survey_share")[1] > 0 else ())
    sharpest = max(span(n)[1] for n in rates)
    if span("target_yaw_rate_max")[0] < sharpest:
        refuse("target_yaw_rate_max", sharpest, "the leader's sharpest commanded turn rate",
               rates + (("leader_survey_share",) if "leader_uturn_rate" in rates else ()))
    if span("leader_uturn_rate")[1] * span("leader_rate_lag_s")[1] >= math.pi:
        names = ("leader_uturn_rate", "leader_rate_lag_s")
        if any(n in rng_map for n in names):
            raise ValueError(f"{shown(names[0])} and {shown(names[1])} are invalid together: a reset can draw "
                             f"leader_uturn_rate * leader_rate_lag_s = "
                             f"{span(names[0])[1] * span(names[1])[1]:g} rad, but every draw must have it < pi "
                             "(a U-turn's command ends when pi - rate * lag remains): narrow the ranges")


def make_config(scenario: str = "S4", disturbance: str | None = None, *, version: str = "v0",
                ranges: Mapping[str, tuple[float, float]] | None = None, tier: str | None = None,
                **overrides: object) -> EnvConfig:
    """Build a validated :class:`EnvConfig` from a preset and keyword overrides.

    Args:
        scenario: "S1".."S4" (Table 2).
        disturbance: "L0".."L2" (Table 3); ``None`` takes the scenario's level.
        version: "v0" (the paper's task) or "v1" (the acoustic link; accepts
            :data:`OVERRIDES_V1` too, and any rangeable field as a ``(min, max)`` range drawn
            at every reset).
        ranges: v1 only: default per-reset ranges (a tier's); overrides replace them.
        tier: v1 only: the tier's name (recorded in the task spec).
        **overrides: any of :data:`OVERRIDES` (``delay_s``, ``episode_s``, ``dt``,
            ``physics_substeps``, ``mismatch``, ``force_limits``, ``init_offset_m``,
            ``max_distance_m``, ``effort_weight``, ``p_d``, ``psi_d``, ``steady_start_s``),
            and on v1 :data:`OVERRIDES_V1`. Numbers may be Python or numpy scalars (not
            bools); tuples may be tuples, lists or arrays. An override of ``None`` is no
            override: the field keeps the preset's value (v1: the field's default, or the
            range in ``ranges``).

    Raises:
        UnknownKeywordError: an override that does not exist (a ``TypeError`` naming it and
            listing the valid ones; also a ``ValueError``).
        ValueError: unknown scenario, level or version, a value of the wrong type, out of its
            range or too large for a float, or ``ranges`` / ``tier`` on v0.
    """
    if not isinstance(scenario, str) or scenario not in SCENARIOS:
        raise ValueError(f"scenario={scenario!r} is unknown: valid scenarios are {sorted(SCENARIOS)}")
    if version not in ("v0", "v1"):
        raise ValueError(f"version={version!r} is unknown: must be 'v0' or 'v1'")
    sc = SCENARIOS[scenario]
    level = sc.disturbance if disturbance is None else disturbance
    if not isinstance(level, str) or level not in DISTURBANCE_LEVELS:
        raise ValueError(f"disturbance={disturbance!r} is unknown: valid levels are "
                         f"{sorted(DISTURBANCE_LEVELS)} (or None for the scenario's own)")
    allowed = OVERRIDES if version == "v0" else OVERRIDES + OVERRIDES_V1
    kw = _parse_overrides(overrides, allowed, version)
    base: dict = {"delay_s": sc.delay_s, "mismatch": sc.mismatch}
    if version == "v0":
        if ranges or tier is not None:
            raise ValueError(f"ranges={ranges!r} / tier={tier!r} are invalid with version='v0': per-reset ranges "
                             f"and tiers exist only on v1")
        return EnvConfig(scenario=sc, disturbance=DISTURBANCE_LEVELS[level], **{**base, **kw})
    if ranges is not None and not isinstance(ranges, Mapping):
        raise ValueError(f"ranges={_short(ranges)} is invalid: must be a mapping of field -> (min, max) or None")
    if tier is not None and not isinstance(tier, str):
        raise ValueError(f"tier={_short(tier)} is invalid: must be a tier's name or None")
    rng_map: dict[str, tuple[float, float]] = {}
    for k, r in (ranges or {}).items():
        if k not in RANGEABLE:
            raise ValueError(f"ranges has {k!r}: only {list(RANGEABLE)} can be drawn per reset")
        lo, hi = as_real_tuple(f"ranges[{k!r}]", r, 2)
        _require(lo <= hi, f"ranges[{k!r}]", r, "a (min, max) range with min <= max")
        rng_map[k] = (lo, hi)
    cond_kw: dict = {}
    env_kw: dict = dict(base)
    for k, v in kw.items():
        if isinstance(v, tuple) and k in RANGEABLE:
            rng_map[k] = v
            continue
        rng_map.pop(k, None)  # a fixed value replaces the tier's range
        (env_kw if k in OVERRIDES else cond_kw)[k] = v
    dt = float(env_kw.get("dt", 0.05))
    defaults = _condition_defaults(sc, dt, float(env_kw["delay_s"]))
    if float(cond_kw.get("leader_modes", 0.0) or 0.0) > 0:  # a leader replaces the scenario's target tones
        defaults.update(target_speed=0.0, target_surge_amp=0.0, target_yaw_rate_amp=0.0)
    for k, v in defaults.items():
        cond_kw.setdefault(k, v)
    if "warmup_s" not in cond_kw:
        def hi(name: str) -> float:
            return rng_map[name][1] if name in rng_map else float(cond_kw.get(name, CONDITION_INDEX[name].default or 0))
        cond_kw["warmup_s"] = min(120.0, hi("latency_s") + 3 * hi("latency_spread_s") + 2 * hi("update_period_s"))
    # validate the ranges with the fields' own bounds: all lower ends, all upper ends, then the
    # base condition at the ranges' midpoints (what the task spec reports)
    for end in (0, 1):
        for k, r in rng_map.items():
            if k == "mismatch":
                _in_range("mismatch", r[end], *BOUNDS["mismatch"][:2])
        Condition(**{**cond_kw, **{k: r[end] for k, r in rng_map.items() if k != "mismatch"}})
    _check_every_draw(rng_map, cond_kw)
    cond = Condition(**{**cond_kw, **{k: 0.5 * (r[0] + r[1]) for k, r in rng_map.items() if k != "mismatch"}})
    if "mismatch" in rng_map:
        env_kw["mismatch"] = 0.5 * sum(rng_map["mismatch"])
    env_kw.setdefault("delay_s", 0.0)
    period = rng_map["update_period_s"] if "update_period_s" in rng_map else cond.update_period_s
    if min(np.atleast_1d(period)) < dt - 1e-12:  # a range is checked at its lower end
        raise ValueError(f"update_period_s={period} is invalid: must be >= dt={dt} s "
                         f"(at most one packet per control step)")
    return EnvConfig(scenario=sc, disturbance=DISTURBANCE_LEVELS[level], condition=cond,
                     ranges=MappingProxyType(dict(rng_map)), tier=tier, **env_kw)


def make_task_spec(scenario: str = "S4", disturbance: str | None = None, **overrides: object) -> TaskSpec:
    """The :class:`TaskSpec` of the env made with the same arguments (``version="v1"`` for v1)."""
    return make_config(scenario, disturbance, **overrides).task_spec()
