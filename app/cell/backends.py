"""The robot backend that the settings select: a simulated UR5e or a real one over RTDE."""

from __future__ import annotations

import numpy as np

from app.cell.clock import Clock
from app.cell.robot import RobotBackend, SimRobot
from app.config import Settings

__all__ = ["make_robot"]


def make_robot(settings: Settings, clock: Clock, *, q0: np.ndarray) -> RobotBackend:
    """The robot backend that ``settings.robot`` selects.

    ``"sim"``: a :class:`~app.cell.robot.SimRobot` at ``q0``. ``"rtde"``: an
    :class:`~app.cell.rtde.backend.RtdeRobot` at ``settings.robot_host``, connected before it is returned
    (``q0`` is ignored: the real arm is where it is).

    Raises:
        RobotConnectionError: ``"rtde"`` and no robot answers at the address.
    """
    if settings.robot == "sim":
        return SimRobot(clock, q0=q0)
    if settings.robot == "rtde":
        from app.cell.rtde.backend import RtdeRobot  # the RTDE modules only when they are used

        robot = RtdeRobot(settings.robot_host, clock=clock)
        robot.connect()
        return robot
    raise ValueError(f"unknown robot backend {settings.robot!r}; expected 'sim' or 'rtde'")
