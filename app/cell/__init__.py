"""What connects to the physical cell: clocks, robot backends, human sources, frame validation.

The common names are re-exported here and imported lazily, so ``import app.cell`` stays cheap (the
RTDE worker process imports only what it needs)::

    from app.cell import SimClock, SimRobot, SimulatedOperator, ValidatedSource
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS: dict[str, str] = {
    "Clock": "app.cell.clock",
    "WallClock": "app.cell.clock",
    "SimClock": "app.cell.clock",
    "RateLoop": "app.cell.clock",
    "JointLimits": "app.cell.joint_tracking",
    "RobotBackend": "app.cell.robot",
    "RobotState": "app.cell.robot",
    "RobotConnectionError": "app.cell.robot",
    "SimRobot": "app.cell.robot",
    "make_robot": "app.cell.backends",
    "RtdeRobot": "app.cell.rtde.backend",
    "HumanSource": "app.cell.source",
    "OperatorParams": "app.cell.operator_sim",
    "SimulatedOperator": "app.cell.operator_sim",
    "ReplaySource": "app.cell.human",
    "StreamSource": "app.cell.human",
    "make_human_source": "app.cell.human",
    "load_replay_clip": "app.cell.human",
    "save_clip": "app.cell.human",
    "FrameRejected": "app.cell.validation",
    "FrameValidator": "app.cell.validation",
    "CellVolume": "app.cell.validation",
    "StaleWatchdog": "app.cell.validation",
    "ValidatedSource": "app.cell.validation",
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
    "load_replay_clip",
    "make_human_source",
    "make_robot",
    "save_clip",
]

if TYPE_CHECKING:
    from app.cell.backends import make_robot
    from app.cell.clock import Clock, RateLoop, SimClock, WallClock
    from app.cell.human import (
        ReplaySource,
        StreamSource,
        load_replay_clip,
        make_human_source,
        save_clip,
    )
    from app.cell.joint_tracking import JointLimits
    from app.cell.operator_sim import OperatorParams, SimulatedOperator
    from app.cell.robot import RobotBackend, RobotConnectionError, RobotState, SimRobot
    from app.cell.rtde.backend import RtdeRobot
    from app.cell.source import HumanSource
    from app.cell.validation import (
        CellVolume,
        FrameRejected,
        FrameValidator,
        StaleWatchdog,
        ValidatedSource,
    )


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'app.cell' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
