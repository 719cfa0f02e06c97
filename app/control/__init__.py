"""The cell runtime: clocks, robot backends, human sources, frame validation (and the supervisor).

The common names are re-exported here and imported lazily, so ``import app.control`` stays cheap (the
RTDE worker process imports only what it needs)::

    from app.control import SimClock, SimRobot, SimulatedOperator, ValidatedSource
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS: dict[str, str] = {
    "Clock": "app.control.clock",
    "WallClock": "app.control.clock",
    "SimClock": "app.control.clock",
    "RateLoop": "app.control.clock",
    "JointLimits": "app.control.joint_tracking",
    "RobotBackend": "app.control.robot",
    "RobotState": "app.control.robot",
    "RobotConnectionError": "app.control.robot",
    "SimRobot": "app.control.robot",
    "make_robot": "app.control.robot",
    "RtdeRobot": "app.control.rtde_process",
    "HumanSource": "app.control.human",
    "OperatorParams": "app.control.operator_sim",
    "SimulatedOperator": "app.control.operator_sim",
    "ReplaySource": "app.control.human",
    "StreamSource": "app.control.human",
    "make_human_source": "app.control.human",
    "load_clip": "app.control.human",
    "save_clip": "app.control.human",
    "FrameRejected": "app.control.validation",
    "FrameValidator": "app.control.validation",
    "CellVolume": "app.control.validation",
    "StaleWatchdog": "app.control.validation",
    "ValidatedSource": "app.control.validation",
}

__all__ = [
    "CellVolume",
    "Clock",
    "FrameRejected",
    "FrameValidator",
    "HumanSource",
    "JointLimits",
    "OperatorParams",
    "RateLoop",
    "ReplaySource",
    "RobotBackend",
    "RobotConnectionError",
    "RobotState",
    "RtdeRobot",
    "SimClock",
    "SimRobot",
    "SimulatedOperator",
    "StaleWatchdog",
    "StreamSource",
    "ValidatedSource",
    "WallClock",
    "load_clip",
    "make_human_source",
    "make_robot",
    "save_clip",
]

if TYPE_CHECKING:
    from app.control.clock import Clock, RateLoop, SimClock, WallClock
    from app.control.human import (
        HumanSource,
        ReplaySource,
        StreamSource,
        load_clip,
        make_human_source,
        save_clip,
    )
    from app.control.joint_tracking import JointLimits
    from app.control.operator_sim import OperatorParams, SimulatedOperator
    from app.control.robot import RobotBackend, RobotConnectionError, RobotState, SimRobot, make_robot
    from app.control.rtde_process import RtdeRobot
    from app.control.validation import (
        CellVolume,
        FrameRejected,
        FrameValidator,
        StaleWatchdog,
        ValidatedSource,
    )


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'app.control' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
