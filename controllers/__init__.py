"""The paper's four controllers as scripted policies (SB3 ``predict`` protocol).

>>> import gymnasium as gym, auv_follow_env
>>> from controllers import make_controller
>>> env = gym.make("AUVFollow-S4-v0")
>>> policy = make_controller("PROPOSED", env.unwrapped.task_spec)
"""

from __future__ import annotations

from auv_follow_env.params import TaskSpec
from controllers.base import ScriptedPolicy
from controllers.hierarchical import Gains, HierarchicalController
from controllers.pid import PIDController, PIDGains

__all__ = ["CONTROLLERS", "make_controller", "ScriptedPolicy", "HierarchicalController", "Gains",
           "PIDController", "PIDGains"]

#: Table 1: (delay prediction, robust terms) of the three variants of the hierarchical law
TABLE_1: dict[str, tuple[bool, bool]] = {
    "ROBUST_ONLY": (False, True),
    "PRED_ONLY": (True, False),
    "PROPOSED": (True, True),
}
CONTROLLERS: tuple[str, ...] = ("PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED")


def make_controller(name: str, spec: TaskSpec, gains: Gains | None = None) -> ScriptedPolicy:
    """One of :data:`CONTROLLERS` for the task ``spec`` (one gain set for the whole study).

    Raises:
        ValueError: unknown name (the message lists the valid ones).
    """
    if name == "PID":
        return PIDController(spec)
    if name not in TABLE_1:
        raise ValueError(f"controller={name!r} is unknown: valid controllers are {list(CONTROLLERS)}")
    prediction, robust = TABLE_1[name]
    return HierarchicalController(spec, prediction=prediction, robust=robust, gains=gains, name=name)
