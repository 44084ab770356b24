"""The v1 tiers: the follower hears its target over an acoustic link.

Each tier is a distribution of conditions: at every ``reset`` the env draws, from its own
generator, one value per ranged field (uniformly between the bounds below) and keeps the
fixed ones. The drawn condition is ``info["condition"]`` at reset.

The numbers are ours (the paper has a constant delay and a perfect channel). They follow
what acoustic positioning of a nearby vehicle looks like: USBL / modem fixes every 0.5-6 s,
latencies of 0.5-5 s from processing and medium-access slots (propagation over a few metres
is negligible), i.i.d. loss probabilities of 0-35 % plus bursts (multipath, bubbles, thruster
noise; measured shares of sends lost in experiments/tier_claims.py),
position noise of centimetres plus about 1-3 % of range; a target whose speed and turn rate
wander as Ornstein-Uhlenbeck processes (no fixed period a history can lock onto); a
Gauss-Markov current with a wandering direction; coloured disturbances; thrusters with a
first-order lag and a rate limit. Difficulty rises monotonically from Easy to Hard in every
field; Extreme is harder than Hard in every field (six of its ranges overlap Hard's, four
share an end value) and is for out-of-distribution testing only.

Test seeds: each tier publishes 100 seeds (:attr:`Tier.test_seeds`) on which it is scored.
Training code must not use them; :func:`check_training_seeds` refuses any seed at or above
:data:`TRAIN_SEED_LIMIT` (every test seed is above it).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from auv_follow_env.params import CONDITION_INDEX, EnvConfig, make_config

__all__ = ["Tier", "TIERS", "LEADER_TIERS", "ALL_TIERS", "TIER_NAMES", "LEADER_TIER_NAMES",
           "TRAIN_SEED_LIMIT", "check_training_seeds", "make_tier_config",
           "make_env_config", "tier_table_markdown", "tier_summary_markdown"]

#: every published test seed is >= this; training seeds must be below it
TRAIN_SEED_LIMIT = 1_000_000


@dataclass(frozen=True)
class Tier:
    """A v1 benchmark tier: fixed settings, per-reset ranges and its published test seeds."""

    name: str
    description: str
    scenario: str  #: preset for the plant, offset and tone disturbances ("S4": nominal vehicle)
    disturbance: str  #: Table 3 level for the tone current and disturbances
    fixed: Mapping[str, object]  #: condition fields set to one value
    ranges: Mapping[str, tuple[float, float]]  #: fields drawn uniformly per reset
    test_seeds: tuple[int, ...]  #: the 100 seeds the leaderboard scores on
    out_of_distribution: bool = False  #: True: for testing only (Extreme)

    @property
    def env_id(self) -> str:
        return f"AUVFollow-{self.name}-v1"


def _seeds(k: int) -> tuple[int, ...]:
    return tuple(range(k * TRAIN_SEED_LIMIT, k * TRAIN_SEED_LIMIT + 100))


_COMMON = {"target_surge_amp": 0.0, "target_yaw_rate_amp": 0.0, "latency_corr_s": 10.0,
           "current_corr_s": 60.0, "disturbance_corr_s": 5.0}

TIERS: Mapping[str, Tier] = MappingProxyType({
    "Easy": Tier(
        name="Easy", scenario="S4", disturbance="L1", test_seeds=_seeds(1),
        description="fast, reliable modem: fixes every 0.5-1 s, 0.5-1 s latency, rare i.i.d. loss",
        fixed=MappingProxyType({
            **_COMMON, "period_jitter_s": 0.05, "latency_model": "uniform", "latency_spread_s": 0.1,
            "fix_sigma_per_m": 0.005, "heading_sigma_rad": 0.01, "velocity_sigma_mps": 0.01,
            "yaw_rate_sigma_radps": 0.002, "target_speed_corr_s": 20.0, "target_yaw_rate_corr_s": 10.0,
            "target_yaw_rate_max": 0.15, "current_speed_std": 0.01, "current_direction_drift": 0.01,
            "thruster_tc_s": 0.1, "warmup_s": 3.0}),
        ranges=MappingProxyType({
            "update_period_s": (0.5, 1.0), "latency_s": (0.5, 1.0), "loss_prob": (0.0, 0.05),
            "fix_sigma_m": (0.01, 0.03), "target_speed": (0.40, 0.50), "target_speed_std": (0.02, 0.04),
            "target_yaw_rate_std": (0.02, 0.04), "current_speed": (0.0, 0.05), "mismatch": (0.15, 0.60)})),
    "Medium": Tier(
        name="Medium", scenario="S4", disturbance="L2", test_seeds=_seeds(2),
        description="USBL at 0.5-1 Hz: correlated 1-2 s latency, 5-15 % loss with short bursts",
        fixed=MappingProxyType({
            **_COMMON, "period_jitter_s": 0.1, "latency_model": "gauss_markov",
            "burst_p_good_bad": 0.05, "burst_p_bad_good": 0.5, "burst_loss_bad": 0.8,
            "fix_sigma_per_m": 0.01, "heading_sigma_rad": 0.02, "velocity_sigma_mps": 0.02,
            "yaw_rate_sigma_radps": 0.005, "target_speed_corr_s": 15.0, "target_yaw_rate_corr_s": 10.0,
            "target_yaw_rate_max": 0.20, "current_speed_std": 0.02, "current_direction_drift": 0.02,
            "disturbance_noise_u": 0.01, "disturbance_noise_v": 0.01, "disturbance_noise_r": 0.005,
            "thruster_tc_s": 0.2, "thruster_rate": 2.0, "warmup_s": 6.0}),
        ranges=MappingProxyType({
            "update_period_s": (1.0, 2.0), "latency_s": (1.0, 2.0), "latency_spread_s": (0.1, 0.3),
            "loss_prob": (0.05, 0.15), "fix_sigma_m": (0.03, 0.06), "target_speed": (0.40, 0.55),
            "target_speed_std": (0.04, 0.08), "target_yaw_rate_std": (0.03, 0.06),
            "current_speed": (0.02, 0.10), "mismatch": (0.30, 1.05)})),
    "Hard": Tier(
        name="Hard", scenario="S4", disturbance="L2", test_seeds=_seeds(3),
        description="shared acoustic channel: fixes every 2-4 s, 1.5-3 s latency, 10-25 % loss in bursts",
        fixed=MappingProxyType({
            **_COMMON, "period_jitter_s": 0.2, "latency_model": "gauss_markov",
            "burst_p_good_bad": 0.1, "burst_loss_bad": 0.9,
            "fix_sigma_per_m": 0.02, "heading_sigma_rad": 0.03, "velocity_sigma_mps": 0.03,
            "yaw_rate_sigma_radps": 0.01, "target_speed_corr_s": 12.0, "target_yaw_rate_corr_s": 8.0,
            "target_yaw_rate_max": 0.25, "current_speed_std": 0.03, "current_direction_drift": 0.03,
            "disturbance_noise_u": 0.02, "disturbance_noise_v": 0.02, "disturbance_noise_r": 0.01,
            "thruster_tc_s": 0.3, "thruster_rate": 1.5, "warmup_s": 9.0}),
        ranges=MappingProxyType({
            "update_period_s": (2.0, 4.0), "latency_s": (1.5, 3.0), "latency_spread_s": (0.2, 0.5),
            "loss_prob": (0.10, 0.25), "burst_p_bad_good": (0.3, 0.5), "fix_sigma_m": (0.05, 0.10),
            "target_speed": (0.40, 0.60), "target_speed_std": (0.06, 0.12),
            "target_yaw_rate_std": (0.05, 0.09), "current_speed": (0.05, 0.15), "mismatch": (0.60, 1.50)})),
    "Extreme": Tier(
        name="Extreme", scenario="S4", disturbance="L2", test_seeds=_seeds(4), out_of_distribution=True,
        description="out of distribution (test only): fixes every 4-6 s, 3-5 s latency, 20-35 % loss, "
                    "long bursts, sharp manoeuvres",
        fixed=MappingProxyType({
            **_COMMON, "period_jitter_s": 0.3, "latency_model": "gauss_markov",
            "burst_p_good_bad": 0.15, "burst_p_bad_good": 0.25, "burst_loss_bad": 1.0,
            "fix_sigma_per_m": 0.03, "heading_sigma_rad": 0.05, "velocity_sigma_mps": 0.05,
            "yaw_rate_sigma_radps": 0.02, "target_speed_corr_s": 10.0, "target_yaw_rate_corr_s": 6.0,
            "target_yaw_rate_max": 0.30, "current_speed_std": 0.05, "current_direction_drift": 0.05,
            "disturbance_noise_u": 0.03, "disturbance_noise_v": 0.03, "disturbance_noise_r": 0.015,
            "thruster_tc_s": 0.5, "thruster_rate": 1.0, "warmup_s": 12.0}),
        ranges=MappingProxyType({
            "update_period_s": (4.0, 6.0), "latency_s": (3.0, 5.0), "latency_spread_s": (0.5, 1.0),
            "loss_prob": (0.20, 0.35), "fix_sigma_m": (0.10, 0.20), "target_speed": (0.45, 0.65),
            "target_speed_std": (0.10, 0.16), "target_yaw_rate_std": (0.08, 0.12),
            "current_speed": (0.10, 0.25), "mismatch": (1.00, 2.00)})),
})

#: the link fields a Leader tier takes from the v1 tier of its level (everything but the target's)
_TARGET_FIELDS = ("target_speed", "target_speed_std", "target_yaw_rate_std", "target_speed_corr_s",
                  "target_yaw_rate_corr_s", "target_yaw_rate_max")

def _leader(level: str, k: int, description: str, fixed: dict, ranges: dict) -> Tier:
    """A Leader tier: the link, current, disturbances and thrusters of the v1 tier ``level``, the
    leader's modes instead of the OU target (docs/tiers.md, "Leader tiers")."""
    base = _V1[level]
    f = {n: v for n, v in base.fixed.items() if n not in _TARGET_FIELDS}
    r = {n: v for n, v in base.ranges.items() if n not in _TARGET_FIELDS}
    f.update({"target_speed": 0.0, "target_yaw_rate_max": 0.5, "leader_survey_share": 0.5, **fixed})
    r.update({"leader_cruise_speed": (0.4, 0.6), **ranges})
    return Tier(name=f"Leader-{level}", scenario=base.scenario, disturbance=base.disturbance, test_seeds=_seeds(k),
                description=description, fixed=MappingProxyType(f), ranges=MappingProxyType(r))


_V1 = TIERS
LEADER_TIERS: Mapping[str, Tier] = MappingProxyType({
    "Leader-Easy": _leader(
        "Easy", 5, "Easy's link; a leader that cruises and turns, or surveys (legs of 10-20 m)",
        {"leader_modes": 1.0},
        {"leader_turn_rate": (0.05, 0.15), "leader_cruise_mean_s": (10.0, 20.0), "leader_turn_mean_s": (5.0, 10.0),
         "leader_leg_m": (10.0, 20.0), "leader_uturn_rate": (0.15, 0.25)}),
    "Leader-Medium": _leader(
        "Medium", 6, "Medium's link; a leader that also loiters and sprints, or surveys; up to 5 % outlier fixes",
        {"leader_modes": 2.0},
        {"leader_turn_rate": (0.08, 0.20), "leader_cruise_mean_s": (8.0, 18.0), "leader_turn_mean_s": (4.0, 10.0),
         "leader_leg_m": (8.0, 18.0), "leader_uturn_rate": (0.15, 0.30), "outlier_share": (0.0, 0.05),
         "leader_loiter_speed": (0.05, 0.15), "leader_sprint_speed": (0.8, 1.0),
         "leader_loiter_mean_s": (5.0, 12.0), "leader_sprint_mean_s": (3.0, 8.0)}),
    "Leader-Hard": _leader(
        "Hard", 7, "Hard's link; sharp manoeuvres (short legs, 0.25-0.4 rad/s U-turns), 5-15 % outlier fixes",
        {"leader_modes": 2.0},
        {"leader_turn_rate": (0.15, 0.30), "leader_cruise_mean_s": (5.0, 12.0), "leader_turn_mean_s": (3.0, 8.0),
         "leader_leg_m": (5.0, 12.0), "leader_uturn_rate": (0.25, 0.40), "outlier_share": (0.05, 0.15),
         "leader_loiter_speed": (0.05, 0.15), "leader_sprint_speed": (0.9, 1.2),
         "leader_loiter_mean_s": (5.0, 12.0), "leader_sprint_mean_s": (3.0, 8.0)}),
})
#: every tier: the OU-target tiers (TIERS) and the Leader tiers (LEADER_TIERS)
ALL_TIERS: Mapping[str, Tier] = MappingProxyType({**TIERS, **LEADER_TIERS})
TIER_NAMES: tuple[str, ...] = tuple(TIERS)
LEADER_TIER_NAMES: tuple[str, ...] = tuple(LEADER_TIERS)


def make_tier_config(tier: str, disturbance: str | None = None, **overrides: object) -> EnvConfig:
    """The :class:`EnvConfig` of ``AUVFollow-<tier>-v1`` with keyword overrides.

    An override with a number fixes that field for every episode; a ``(min, max)`` pair
    replaces its range. Any v0 or v1 override is accepted (see ``make_config``). An override
    of ``None`` is no override: the tier keeps its own fixed value or range for that field
    (``loss_prob=None`` on Hard still draws the loss in [0.10, 0.25]); where the tier sets
    none, the field's default applies as on ``AUVFollow-v1``.

    Raises:
        UnknownKeywordError: an override that does not exist (a TypeError; also a ValueError).
        ValueError: unknown tier or a bad override value.
    """
    if not isinstance(tier, str) or tier not in ALL_TIERS:
        raise ValueError(f"tier={tier!r} is unknown: valid tiers are {list(ALL_TIERS)}")
    t = ALL_TIERS[tier]
    # (a None for a field the tier does not set, or for an unknown keyword, goes on to make_config,
    # which leaves the first out and refuses the second)
    given = {k: v for k, v in overrides.items() if v is not None or (k not in t.fixed and k not in t.ranges)}
    kw = {**t.fixed, **given}
    ranges = {k: v for k, v in t.ranges.items() if k not in given}
    return make_config(t.scenario, disturbance if disturbance is not None else t.disturbance, version="v1",
                       ranges=ranges, tier=t.name, **kw)


def check_training_seeds(seeds: Iterable[int], *, name: str = "seeds") -> list[int]:
    """Return ``seeds`` as a list, refusing any that is not allowed for training.

    Raises:
        ValueError: a seed >= :data:`TRAIN_SEED_LIMIT` (where every tier's test seeds lie),
            negative or not an integer.
    """
    out = []
    for s in seeds:
        if isinstance(s, bool) or not hasattr(s, "__index__"):
            raise ValueError(f"{name} contains {s!r}: seeds must be integers")
        s = int(s)
        if s < 0 or s >= TRAIN_SEED_LIMIT:
            raise ValueError(f"{name} contains {s}: training seeds must be in [0, {TRAIN_SEED_LIMIT}); "
                             f"seeds >= {TRAIN_SEED_LIMIT} are reserved for the tiers' test sets")
        out.append(s)
    return out


def _fmt(v: object) -> str:
    if isinstance(v, tuple):
        return f"U[{v[0]:g}, {v[1]:g}]"
    return f"{v:g}" if isinstance(v, float) else str(v)


def tier_table_markdown() -> str:
    """One Markdown table per tier: every v1 field that differs from v0's default, with unit."""
    out = []
    for t in ALL_TIERS.values():
        out.append(f"### {t.env_id}: {t.description}\n")
        out.append(f"Plant {t.scenario} (nominal vehicle), tone disturbances {t.disturbance}; test seeds "
                   f"{t.test_seeds[0]}-{t.test_seeds[-1]}{' (test only)' if t.out_of_distribution else ''}.\n")
        out.append("| field | value | unit |")
        out.append("|---|---|---|")
        merged = {**t.fixed, **t.ranges}
        for name in list(CONDITION_INDEX) + ["latency_model", "mismatch"]:
            if name in merged:
                unit = CONDITION_INDEX[name].unit if name in CONDITION_INDEX else "-"
                out.append(f"| {name} | {_fmt(merged[name])} | {unit} |")
        out.append("")
    return "\n".join(out)


def make_env_config(scenario: str = "S4", disturbance: str | None = None, *, version: str = "v0",
                    tier: str | None = None, **overrides: object) -> EnvConfig:
    """The config of any registered id: a tier (``tier=``), a v1 custom link
    (``version="v1"``) or the paper's v0 task. Used by the single and the vector env."""
    if tier is not None:
        if version != "v1":
            raise ValueError(f"tier={tier!r} needs version='v1' (got version={version!r})")
        own = ALL_TIERS[tier].scenario if isinstance(tier, str) and tier in ALL_TIERS else None
        if own is not None and scenario != own:
            raise ValueError(f"scenario={scenario!r} is invalid on the tier AUVFollow-{tier}-v1: its plant is "
                             f"{own!r}; for another scenario use AUVFollow-v1 (scenario=..., any link setting)")
        return make_tier_config(tier, disturbance, **overrides)
    return make_config(scenario, disturbance, version=version, **overrides)


#: the columns of :func:`tier_summary_markdown`: (header, fields shown, unit)
_SUMMARY = (("fix period", ("update_period_s",), "s"), ("latency model", ("latency_model",), "-"),
            ("latency (mean; spread)", ("latency_s", "latency_spread_s"), "s"),
            ("i.i.d. loss", ("loss_prob",), "-"), ("bursts p_gb / p_bg / loss", ("burst_p_good_bad", "burst_p_bad_good",
                                                                                 "burst_loss_bad"), "-"),
            ("fix sigma", ("fix_sigma_m", "fix_sigma_per_m"), "m; m/m"),
            ("target speed; its OU std", ("target_speed", "target_speed_std"), "m/s"),
            ("turn-rate OU std", ("target_yaw_rate_std",), "rad/s"), ("GM current", ("current_speed",), "m/s"),
            ("mismatch", ("mismatch",), "-"), ("thruster lag", ("thruster_tc_s",), "s"),
            ("leader modes; outliers", ("leader_modes", "outlier_share"), "-"))


def tier_summary_markdown() -> str:
    """One table, a row per tier, of the fields that set its difficulty (U[a, b]: drawn per reset)."""
    head = "| tier | " + " | ".join(f"{h} [{u}]" for h, _, u in _SUMMARY) + " | test seeds |"
    lines = [head, "|" + "---|" * (len(_SUMMARY) + 2)]
    for t in ALL_TIERS.values():
        merged = {**t.fixed, **t.ranges}
        cells = []
        for _, names, _ in _SUMMARY:
            vals = []
            for n in names:
                v = merged.get(n, CONDITION_INDEX[n].default if n in CONDITION_INDEX else None)
                vals.append(_fmt(v) if v is not None else "-")
            cells.append("; ".join(vals) if len(names) < 3 else " / ".join(vals))
        label = f"`{t.env_id}`" + (" (OOD, test only)" if t.out_of_distribution else "")
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {t.test_seeds[0]}-{t.test_seeds[-1]} |")
    return "\n".join(lines) + "\n"
