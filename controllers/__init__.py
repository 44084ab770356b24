"""The paper's four controllers as scripted policies (SB3 ``predict`` protocol), and our
stronger classical baselines beside them (:data:`EXTENDED_CONTROLLERS`, not the paper's).

>>> import gymnasium as gym, auv_follow_env
>>> from controllers import make_controller
>>> env = gym.make("AUVFollow-S4-v0")
>>> policy = make_controller("PROPOSED", env.unwrapped.task_spec)
"""

from __future__ import annotations

from auv_follow_env.params import TaskSpec
from controllers.base import ScriptedPolicy
from controllers.disturbance import DisturbanceObserver
from controllers.estimator import EstimatorConfig, TargetEstimator
from controllers.hierarchical import Gains, HierarchicalController
from controllers.pid import PIDController, PIDGains

__all__ = ["CONTROLLERS", "EXTENDED_CONTROLLERS", "ALL_CONTROLLERS", "make_controller", "ScriptedPolicy",
           "HierarchicalController", "Gains", "PIDController", "PIDGains", "TargetEstimator", "EstimatorConfig",
           "DisturbanceObserver", "DOB_TIME_CONSTANT"]

#: Table 1: (delay prediction, robust terms) of the three variants of the hierarchical law
TABLE_1: dict[str, tuple[bool, bool]] = {
    "ROBUST_ONLY": (False, True),
    "PRED_ONLY": (True, False),
    "PROPOSED": (True, True),
}
#: the paper's four controllers (Table 1), exactly as printed
CONTROLLERS: tuple[str, ...] = ("PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED")
#: OURS, not the paper's: stronger classical baselines (issue 11)
#:
#: * ``PROPOSED_KF``: PROPOSED with the target Kalman filter (:mod:`controllers.estimator`)
#:   in place of the predictor (13)-(17);
#: * ``PROPOSED_KF_DOB``: the same plus the inner-loop disturbance observer
#:   (:mod:`controllers.disturbance`);
#: * ``MPC``: delay-aware MPC on the nominal model over the same estimator, with the same
#:   disturbance observer's estimate as a constant force in its model (offset-free MPC) and the
#:   task's thrusters (lag, rate limit) in its model and constraints, solved for all envs at once
#:   (:mod:`controllers.mpc`).
EXTENDED_CONTROLLERS: tuple[str, ...] = ("PROPOSED_KF", "PROPOSED_KF_DOB", "MPC")
ALL_CONTROLLERS: tuple[str, ...] = CONTROLLERS + EXTENDED_CONTROLLERS
#: time constant of the disturbance observer's low-pass filter [s] (ours; tuned on seeds 100-119)
DOB_TIME_CONSTANT = 0.5


def make_controller(name: str, spec: TaskSpec, gains: Gains | None = None) -> ScriptedPolicy:
    """One of :data:`ALL_CONTROLLERS` for the task ``spec`` (one gain set for the whole study).

    The paper's four (:data:`CONTROLLERS`) are built exactly as before; the extended ones
    (:data:`EXTENDED_CONTROLLERS`, ours) share the same :class:`Gains` where they use the
    hierarchical law.

    Raises:
        ValueError: unknown name (the message lists the valid ones).
    """
    if name == "PID":
        return PIDController(spec)
    if name in TABLE_1:
        prediction, robust = TABLE_1[name]
        return HierarchicalController(spec, prediction=prediction, robust=robust, gains=gains, name=name)
    if name in ("PROPOSED_KF", "PROPOSED_KF_DOB"):
        dob = (DisturbanceObserver(spec.nominal, spec.dt, spec.force_limits, DOB_TIME_CONSTANT)
               if name == "PROPOSED_KF_DOB" else None)
        return HierarchicalController(spec, prediction=True, robust=True, gains=gains, name=name,
                                      estimator=TargetEstimator(spec), disturbance_observer=dob)
    if name == "MPC":
        from controllers.mpc import MPCController

        return MPCController(spec, name=name)
    raise ValueError(f"controller={name!r} is unknown: valid controllers are {list(ALL_CONTROLLERS)}")
