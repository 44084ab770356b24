"""Parameters of the plant and the task as frozen values.

Every number here that the paper does not give is *our choice*; the comment beside it
says so and gives its unit. Presets (scenarios S1-S4, disturbance levels L0-L2) are
written once, here; variants are made with :func:`dataclasses.replace` or through the
environment's keyword overrides, which build a validated :class:`EnvConfig`.

Sources: Zhang et al., J. Mar. Sci. Eng. 2026, 14(11), 963, Tables 2-3 and eq. (63);
``shared/paper/NOTES.md`` for the restored signs and suggested values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType

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
]


def _require(cond: bool, name: str, value: object, allowed: str) -> None:
    if not cond:
        raise ValueError(f"{name}={value!r} is invalid: must be {allowed}")


def _finite_positive(obj: object, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _require(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, n, v,
                 "a finite number > 0")


def _finite_nonneg(obj: object, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _require(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0, n, v,
                 "a finite number >= 0")


@dataclass(frozen=True, kw_only=True)
class VehicleParams:
    """Planar 3-DOF vehicle, eqs. (6)-(8). The paper gives no values; these are ours.

    A small ROV with added mass included; linear damping stands in for quadratic drag
    near 0.5 m/s (NOTES.md, suggested values).
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
    (NOTES.md, suggested values), rising from S1 to S4.
    """

    speed: float  #: mean surge speed v_bar [m/s] (Table 2)
    surge_amp: float  #: relative surge-speed modulation a_u [-] (our choice)
    surge_period: float  #: period of the speed change P_u [s] (our choice)
    yaw_rate_amp: float  #: yaw-rate amplitude a_r [rad/s] (our choice)
    yaw_period: float  #: period of the turns P_r [s] (our choice)

    def __post_init__(self) -> None:
        _finite_positive(self, "speed", "surge_period", "yaw_period")
        _finite_nonneg(self, "yaw_rate_amp")
        _require(isinstance(self.surge_amp, (int, float)) and 0 <= self.surge_amp < 1,
                 "surge_amp", self.surge_amp, "in [0, 1)")


@dataclass(frozen=True, kw_only=True)
class DisturbanceLevel:
    """Table 3: current ranges (inertial x/y components of v_c^I) and peaks of the lumped
    disturbances (d_u, d_v, d_r).

    The peaks are read per unit mass (our reading; NOTES.md): the plant receives the
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
            lo, hi = getattr(self, n)
            _require(math.isfinite(lo) and math.isfinite(hi) and lo <= hi, n,
                     getattr(self, n), "a finite (min, max) with min <= max")
        _require(len(self.peaks) == 3 and all(math.isfinite(p) and p >= 0 for p in self.peaks),
                 "peaks", self.peaks, "three finite numbers >= 0")


# Table 3, signs restored as in NOTES.md (sway ranges were printed out of order).
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
    mismatch: float  #: true damping = nominal * (1 + mismatch) [-] (our choice, NOTES.md)
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


@dataclass(frozen=True, kw_only=True)
class EnvConfig:
    """Everything that defines one AUVFollow task. Built by :func:`make_config`.

    Attributes are documented with units; values marked "ours" are our choices.
    """

    scenario: Scenario
    disturbance: DisturbanceLevel
    delay_s: float  #: target-state delay tau [s]; a multiple of ``dt``
    mismatch: float  #: true damping = nominal * (1 + mismatch) [-]; > -1
    nominal: VehicleParams = NOMINAL_VEHICLE  #: what controllers are told
    dt: float = 0.05  #: control step [s] (ours: 20 Hz)
    physics_substeps: int = 2
    """RK4 substeps per control step (ours: 0.025 s; measured over a 60 s S4 run, the pose
    differs from a 40-substep solution by < 1e-7 m, so the physics is converged)."""
    episode_s: float = 60.0  #: episode length [s] (ours, NOTES.md)
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

    def __post_init__(self) -> None:
        _finite_positive(self, "dt", "episode_s", "init_offset_m", "max_distance_m")
        _finite_nonneg(self, "delay_s", "steady_start_s", "effort_weight", "init_offset_m")
        _require(isinstance(self.physics_substeps, int) and not isinstance(self.physics_substeps, bool)
                 and self.physics_substeps >= 1, "physics_substeps", self.physics_substeps,
                 "an integer >= 1")
        steps = self.delay_s / self.dt
        _require(abs(steps - round(steps)) < 1e-9 * max(1.0, steps), "delay_s", self.delay_s,
                 f"a multiple of dt={self.dt} s (the delay line holds whole control steps)")
        n = self.episode_s / self.dt
        _require(abs(n - round(n)) < 1e-9 * max(1.0, n) and round(n) >= 1, "episode_s",
                 self.episode_s, f"a positive multiple of dt={self.dt} s")
        _require(isinstance(self.mismatch, (int, float)) and math.isfinite(self.mismatch)
                 and self.mismatch > -1, "mismatch", self.mismatch, "a finite number > -1")
        _require(len(self.force_limits) == 3 and all(
            isinstance(f, (int, float)) and math.isfinite(f) and f > 0 for f in self.force_limits),
            "force_limits", self.force_limits, "three finite numbers > 0")
        _require(len(self.p_d) == 2 and all(math.isfinite(v) for v in self.p_d), "p_d", self.p_d,
                 "two finite numbers [m]")
        _require(math.isfinite(self.psi_d), "psi_d", self.psi_d, "a finite angle [rad]")

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

    def task_spec(self) -> "TaskSpec":
        return TaskSpec(
            scenario=self.scenario.name, disturbance=self.disturbance.name, dt=self.dt,
            delay_s=self.delay_s, delay_steps=self.delay_steps, p_d=self.p_d, psi_d=self.psi_d,
            nominal=self.nominal, force_limits=self.force_limits, episode_s=self.episode_s,
            n_steps=self.n_steps, steady_start_s=self.steady_start_s)


@dataclass(frozen=True, kw_only=True)
class TaskSpec:
    """The static facts a controller may use besides the observation.

    A real follower knows these (its delay, its desired offset, its own nominal model, its
    control rate); it does not know the true damping, the current's future or the target's
    present state. Exposed as ``env.unwrapped.task_spec`` and by :func:`make_task_spec`.
    """

    scenario: str
    disturbance: str
    dt: float  #: control step [s]
    delay_s: float  #: tau [s]
    delay_steps: int  #: tau / dt
    p_d: tuple[float, float]  #: reference offset in the target body frame [m]
    psi_d: float  #: heading offset [rad]
    nominal: VehicleParams  #: nominal m, I_z, X_u, Y_v, N_r given to the controllers
    force_limits: tuple[float, float, float]  #: action +-1 <-> (F_u, F_v, F_r) [N, N, N m]
    episode_s: float  #: episode length [s]
    n_steps: int  #: control steps per episode
    steady_start_s: float  #: start of the steady-state metric window [s]


#: keyword overrides accepted by the environments (and by make_config)
OVERRIDES: tuple[str, ...] = tuple(
    f.name for f in fields(EnvConfig) if f.name not in ("scenario", "disturbance", "nominal"))


def make_config(scenario: str = "S4", disturbance: str | None = None, **overrides: object) -> EnvConfig:
    """Build a validated :class:`EnvConfig` from a preset and keyword overrides.

    Args:
        scenario: "S1".."S4" (Table 2).
        disturbance: "L0".."L2" (Table 3); ``None`` takes the scenario's level.
        **overrides: any of :data:`OVERRIDES` (``delay_s``, ``episode_s``, ``dt``,
            ``physics_substeps``, ``mismatch``, ``force_limits``, ``init_offset_m``,
            ``max_distance_m``, ``effort_weight``, ``p_d``, ``psi_d``, ``steady_start_s``).

    Raises:
        ValueError: unknown scenario, level or override, or a non-physical value.
    """
    if not isinstance(scenario, str) or scenario not in SCENARIOS:
        raise ValueError(f"scenario={scenario!r} is unknown: valid scenarios are {sorted(SCENARIOS)}")
    sc = SCENARIOS[scenario]
    level = sc.disturbance if disturbance is None else disturbance
    if not isinstance(level, str) or level not in DISTURBANCE_LEVELS:
        raise ValueError(f"disturbance={disturbance!r} is unknown: valid levels are "
                         f"{sorted(DISTURBANCE_LEVELS)} (or None for the scenario's own)")
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        raise ValueError(f"unknown override(s) {unknown}: valid overrides are {list(OVERRIDES)}")
    kw: dict = {"delay_s": sc.delay_s, "mismatch": sc.mismatch}
    for k, v in overrides.items():
        if v is None:
            continue
        if k in ("force_limits", "p_d") and not isinstance(v, tuple):
            try:
                v = tuple(float(x) for x in v)  # type: ignore[union-attr]
            except TypeError as exc:
                raise ValueError(f"{k}={v!r} is invalid: must be a sequence of numbers") from exc
        elif k == "physics_substeps":
            pass
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"{k}={v!r} is invalid: must be a number")
        else:
            v = float(v)
        kw[k] = v
    return EnvConfig(scenario=sc, disturbance=DISTURBANCE_LEVELS[level], **kw)


def make_task_spec(scenario: str = "S4", disturbance: str | None = None, **overrides: object) -> TaskSpec:
    """The :class:`TaskSpec` of the env ``AUVFollow-v0`` made with the same arguments."""
    return make_config(scenario, disturbance, **overrides).task_spec()


