"""The robot's stopping model: how long the UR5e takes to stop, and how far it goes meanwhile.

One model for the whole cell: the supervisor's brake, the speed governor's stopping time, the ground-truth
monitor's ``S_s`` and the simulated robot's stop all read :data:`UR5E_STOP`.

The model is a controlled stop along the path (ISO 10218-1 stop category 1/2: the controller decelerates
the arm on its path): the fastest point of the robot decelerates at ``decel_mps2`` and no joint faster than
``joint_decel_radps2``, after ``delay_s``. So for a robot whose fastest point moves at ``v`` and fastest
joint at ``w``:

    T_s = delay_s + max(v / decel_mps2, w / joint_decel_radps2)
    S_s = v_part * (delay_s + (T_s - delay_s) / 2)      (a part moving at v_part toward the person)

Source of the numbers. The UR5 CB3 user manual (stopping time and distance, stop category 0, full
extension, 5 kg payload, 183 deg/s) gives 0.53 s and 0.70 rad for the shoulder (2.7 m/s at the 0.85 m
reach: a mean deceleration of 5.1 m/s^2), 0.24 s and 0.31 rad for the base and 0.16 s and 0.22 rad for the
elbow; the UR5e hardware manual's category 1 and 2 graphs lie in the same range at full speed. This model
takes 3 m/s^2 and 3 rad/s^2, about 60 % of the manual's worst-case mean deceleration (the margin covers
payload, extension and the controller's ramp), with no extra delay: the time until the controller starts
braking is in the reaction time ``T_r`` (see :meth:`reaction_time_s`), not here. Measure your arm's stops
(the robot's log of a protective stop gives both figures) and set these numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["UR5E_STOP", "StoppingModel", "reaction_time_s"]


@dataclass(frozen=True, slots=True)
class StoppingModel:
    """A controlled stop along the path: constant deceleration after a delay.

    Attributes:
        decel_mps2: Deceleration of the robot's fastest point (m/s^2).
        joint_decel_radps2: Largest joint deceleration (rad/s^2).
        delay_s: Time from the stop decision to the start of braking beyond the reaction time ``T_r`` (s).
    """

    decel_mps2: float = 3.0
    joint_decel_radps2: float = 3.0
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("decel_mps2", "joint_decel_radps2"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"StoppingModel.{name} must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.delay_s) and 0.0 <= self.delay_s <= 1.0):
            raise ValueError(f"StoppingModel.delay_s must be in [0, 1] s, got {self.delay_s!r}")

    def stop_time_s(
        self, v_top_mps: float | np.ndarray, w_top_radps: float | np.ndarray = 0.0
    ) -> float | np.ndarray:
        """``T_s`` (s) of a robot whose fastest point moves at ``v_top_mps`` and fastest joint at
        ``w_top_radps``. Element-wise."""
        brake = np.maximum(
            np.maximum(v_top_mps, 0.0) / self.decel_mps2,
            np.maximum(w_top_radps, 0.0) / self.joint_decel_radps2,
        )
        out = self.delay_s + brake
        return float(out) if np.ndim(out) == 0 else out

    def stop_distance_m(
        self, v_part_mps: float | np.ndarray, t_stop_s: float | np.ndarray
    ) -> float | np.ndarray:
        """``S_s`` (m): how far a part moving at ``v_part_mps`` goes during a stop of ``t_stop_s`` (its speed
        falls linearly to 0 over the braking part of the stop). Element-wise."""
        brake = np.maximum(np.asarray(t_stop_s, dtype=np.float64) - self.delay_s, 0.0)
        out = np.maximum(v_part_mps, 0.0) * (self.delay_s + 0.5 * brake)
        return float(out) if np.ndim(out) == 0 else out


#: The stopping model of the UR5e in this project (see the module docstring for the source of the numbers).
UR5E_STOP = StoppingModel()


def reaction_time_s(
    *, tracker_latency_s: float, frame_period_s: float, processing_s: float, servo_period_s: float
) -> float:
    """``T_r`` (s) of ISO/TS 15066 for this system: from the person moving to the robot starting to stop.

    The sum of the tracker's latency (capture to delivery), one frame period (the motion may start just after
    a capture), the processing (validation, forecast, decision) and one controller cycle (the command goes
    out at the next servo tick)."""
    parts = {
        "tracker_latency_s": tracker_latency_s,
        "frame_period_s": frame_period_s,
        "processing_s": processing_s,
        "servo_period_s": servo_period_s,
    }
    for name, v in parts.items():
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"reaction_time_s: {name} must be a finite number >= 0, got {v!r}")
    return float(sum(parts.values()))
