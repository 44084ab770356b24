"""Compatibility: the names ``agents.train`` offered before training became the
``agents.training`` package (``from agents.train import train, load_agent`` keeps working): the
same objects as ``agents.training`` exports, listed once there."""

from __future__ import annotations

import agents.training as _training

__all__ = list(_training.__all__)
globals().update({_name: getattr(_training, _name) for _name in __all__})
