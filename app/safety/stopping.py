"""The robot's stopping model: how long the UR5e takes to stop, and how far it goes meanwhile.

One model for the whole cell: the supervisor's brake, the speed governor's stopping time, the ground-truth
monitor's ``S_s`` and the simulated robot's stop all read :data:`UR5E_STOP`.

The model is a controlled stop along the path (ISO 10218-1 stop category 1/2: the controller decelerates
the arm on its path, all joints stopping together): the fastest point of the robot decelerates at
``decel_mps2`` and joint ``j`` at no more than ``joint_decel_radps2[j]``, after ``delay_s``. So for a robot
whose fastest point moves at ``v`` and whose joints move at ``qd``:

    T_s = delay_s + max(v / decel_mps2, max_j |qd_j| / joint_decel_radps2[j])
    S_s = v_part * (delay_s + (T_s - delay_s) / 2)      (a part moving at v_part toward the person)

The joints' term is ``w / a_min`` with ``w`` the *braking joint speed* (:meth:`StoppingModel.braking_speed`:
each joint's speed weighted by ``a_min / a_j``, ``a_min`` the slowest joint's deceleration), so the compiled
loops keep one scalar per sample.

Source of the numbers. The UR5 CB3 user manual (stopping time and distance, stop category 0, full
extension, 5 kg payload, 183 deg/s = 3.19 rad/s) gives 0.53 s for the shoulder (a mean deceleration of
6.0 rad/s^2; 2.7 m/s at the 0.85 m reach: 5.1 m/s^2), 0.244 s for the base (13.1 rad/s^2) and 0.164 s for the
elbow (19.5 rad/s^2); the UR5e hardware manual's category 1 and 2 graphs lie in the same range at full
speed. This model takes 60 % of each (the margin covers the controller's ramp; the manual's figures are
already the worst case of payload and extension): 3 m/s^2 for the fastest point, 7.86 rad/s^2 for the base,
3.6 for the shoulder and 11.7 for the elbow. The manual publishes no figure for the wrists, which move the
least inertia; they take the base's. No extra delay: the time until the controller starts braking is in
the reaction time ``T_r`` (see :meth:`reaction_time_s`), not here. Measure your arm's stops (the robot's
log of a protective stop gives both figures) and set these numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "MANUAL_DECEL_SHARE",
    "UR5E_STOP",
    "UR5_MANUAL_JOINT_DECEL_RADPS2",
    "StoppingModel",
    "reaction_time_s",
]


#: Mean decelerations (rad/s^2) of the UR5's joints in the manual's category-0 stops (see the module
#: docstring): base, shoulder, elbow; the wrists (no published figure) take the base's.
UR5_MANUAL_JOINT_DECEL_RADPS2 = (13.1, 6.0, 19.5, 13.1, 13.1, 13.1)

#: The share of the manual's decelerations this model counts on (see the module docstring).
MANUAL_DECEL_SHARE = 0.6


@dataclass(frozen=True, slots=True)
class StoppingModel:
    """A controlled stop along the path: constant deceleration after a delay.

    Attributes:
        decel_mps2: Deceleration of the robot's fastest point (m/s^2).
        joint_decel_radps2: Each joint's deceleration (6,) (rad/s^2); a single number: the same for all.
        delay_s: Time from the stop decision to the start of braking beyond the reaction time ``T_r`` (s).
    """

    decel_mps2: float = 3.0
    joint_decel_radps2: float | tuple[float, ...] = tuple(
        round(MANUAL_DECEL_SHARE * a, 2) for a in UR5_MANUAL_JOINT_DECEL_RADPS2
    )
    delay_s: float = 0.0
    _weights: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = self.decel_mps2
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise ValueError(f"StoppingModel.decel_mps2 must be a finite number > 0, got {v!r}")
        raw = self.joint_decel_radps2
        per = (raw,) * 6 if isinstance(raw, int | float) else tuple(raw)
        if len(per) != 6 or not all(isinstance(a, int | float) and math.isfinite(a) and a > 0 for a in per):
            raise ValueError(
                f"StoppingModel.joint_decel_radps2 must be a finite number > 0 or six of them, got {raw!r}"
            )
        if not (math.isfinite(self.delay_s) and 0.0 <= self.delay_s <= 1.0):
            raise ValueError(f"StoppingModel.delay_s must be in [0, 1] s, got {self.delay_s!r}")
        per = tuple(float(a) for a in per)
        object.__setattr__(self, "joint_decel_radps2", per)
        weights = min(per) / np.asarray(per, dtype=np.float64)
        weights.setflags(write=False)
        object.__setattr__(self, "_weights", weights)

    @property
    def slowest_joint_decel_radps2(self) -> float:
        """``a_min``: the deceleration (rad/s^2) of the joint that brakes slowest."""
        return float(min(self.joint_decel_radps2))  # type: ignore[arg-type]

    @property
    def joint_weights(self) -> np.ndarray:
        """(6,) ``a_min / a_j``: each joint's speed in units of the slowest-braking joint's."""
        return self._weights

    def braking_speed(self, qd: np.ndarray) -> np.ndarray | float:
        """The braking joint speed (rad/s) of joint velocities ``qd`` (..., 6): ``max_j |qd_j| a_min / a_j``,
        so that the joints stop in ``braking_speed / a_min`` (s). Over the last axis."""
        out = np.max(np.abs(np.asarray(qd, dtype=np.float64)) * self._weights, axis=-1)
        return float(out) if np.ndim(out) == 0 else out

    def stop_time_s(
        self, v_top_mps: float | np.ndarray, w_top_radps: float | np.ndarray = 0.0
    ) -> float | np.ndarray:
        """``T_s`` (s) of a robot whose fastest point moves at ``v_top_mps`` and whose braking joint speed
        (:meth:`braking_speed`) is ``w_top_radps``. Element-wise."""
        brake = np.maximum(
            np.maximum(v_top_mps, 0.0) / self.decel_mps2,
            np.maximum(w_top_radps, 0.0) / self.slowest_joint_decel_radps2,
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
