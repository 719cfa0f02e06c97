"""ISO/TS 15066 speed and separation monitoring (SSM): the protective separation distance and speed scaling.

ISO/TS 15066:2016, clause 5.5.4.2.3, gives the protective separation distance at time ``t0``:

    S_p = S_h + S_r + S_s + C + Z_d + Z_r

with (constant speeds, the form the standard itself uses as the simplest compliant choice)

- ``S_h = v_h * (T_r + T_s)``: how far the person moves while the robot reacts and stops,
- ``S_r = v_r * T_r``: how far the robot moves during its reaction time,
- ``S_s = v_r * T_s / 2``: the robot's stopping distance, assuming a constant deceleration from ``v_r`` to
  rest within the stopping time ``T_s`` (the integral of the speed over ``T_s``),
- ``C``: the intrusion distance (parts of the body that reach beyond what the sensor detects),
- ``Z_d``: the person's position uncertainty (the sensing system), ``Z_r``: the robot's position uncertainty.

Distances in this project are *surface to surface* between the robot's and the person's capsule models
(see :mod:`app.planning.collision`), so the capsules already cover the limbs' volume and ``C`` only has to
cover what sticks out of them (fingers, loose clothing).

How the parts of the app use this module:

- The supervisor applies the full ``S_p`` to the *current* pose of the person and scales the robot's speed
  with :func:`speed_scale` (the paper's *Nominal Execution*).
- The planner replaces the worst-case ``S_h`` term by the *forecast* of the person over the horizon and
  requires :func:`forecast_clearance` = ``S_r + S_s + C + Z_r + max(Z_d, margin)`` from the forecast pose
  at every sampled instant of a motion, ``margin`` being the forecast's own error margin at that instant
  and ``S_s`` the stopping model's (:mod:`app.safety.stopping`), as the governor's and the monitor's
  (see :mod:`app.planning.search`).

All lengths in metres, speeds in m/s, times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.safety.stopping import UR5E_STOP, StoppingModel


@dataclass(frozen=True, slots=True)
class SSMParams:
    """Parameters of ISO/TS 15066 speed and separation monitoring.

    Defaults and where they come from:

    - ``v_human_mps = 1.6``: ISO/TS 15066 5.5.4.2.3 (by reference to ISO 13855) uses 1.6 m/s for the
      walking speed of a person when it is not measured.
    - ``t_reaction_s = 0.10``: ``T_r``, the time from the person moving to the robot starting to stop:
      one camera frame (33 ms at 30 Hz) + skeleton tracking latency + our processing, + the UR5e controller
      cycle (2 ms at 500 Hz). Measure it on the real installation and set it.
    - ``t_stop_s = 0.20``: ``T_s``, the robot's stopping time at the speeds and payloads of this task
      (TCP <= ~1 m/s, a gripper and a light block). The UR5e hardware manual (section 9, "Stopping time and
      stopping distance", category 1 and 2 graphs) gives stopping times that grow with speed, extension and
      payload; the UR5 CB3 manual's worst case (category 0, full extension, 5 kg, 183 deg/s) is 0.53 s for
      the shoulder, 0.24 s for the base and 0.16 s for the elbow. Use 0.53 for a worst-case configuration.
      Only the standard's constant-speed law uses it (:func:`protective_separation`, :func:`speed_scale`,
      :func:`max_safe_speed`); the planner's clearance, the governor's envelope and the ground-truth monitor
      take ``T_s`` from the robot's current speed with the stopping model (:mod:`app.safety.stopping`).
    - ``intrusion_m = 0.05``: ``C``. ISO 13855 derives C from the sensor's detection capability; with a
      skeleton tracker and body capsules only fingers and clothing reach beyond the model.
    - ``z_human_m = 0.05``: ``Z_d``, the skeleton tracker's position error (a few cm for a ZED2 at 1-2 m).
    - ``z_robot_m = 0.01``: ``Z_r``, the robot's position uncertainty (UR5e repeatability is 0.03 mm; the
      rest covers the capsule model and the calibration of the camera to the robot base).

    Attributes:
        v_human_mps: ``v_h``, the person's speed toward the robot (m/s).
        t_reaction_s: ``T_r``, reaction time of the robot system (s).
        t_stop_s: ``T_s``, stopping time of the robot (s).
        intrusion_m: ``C``, intrusion distance (m).
        z_human_m: ``Z_d``, position uncertainty of the person (m).
        z_robot_m: ``Z_r``, position uncertainty of the robot (m).
    """

    v_human_mps: float = 1.6
    t_reaction_s: float = 0.10
    t_stop_s: float = 0.20
    intrusion_m: float = 0.05
    z_human_m: float = 0.05
    z_robot_m: float = 0.01

    def __post_init__(self) -> None:
        for name in ("v_human_mps", "t_reaction_s", "t_stop_s", "intrusion_m", "z_human_m", "z_robot_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"SSMParams.{name} must be a finite number >= 0, got {value!r}")
        if self.t_reaction_s + self.t_stop_s / 2 <= 0.0:
            raise ValueError("SSMParams: t_reaction_s + t_stop_s / 2 must be > 0 (robot speed is unbounded)")

    @property
    def constant_m(self) -> float:
        """``C + Z_d + Z_r`` (m): the part of ``S_p`` that depends on neither speed."""
        return self.intrusion_m + self.z_human_m + self.z_robot_m

    @property
    def robot_time_s(self) -> float:
        """``T_r + T_s / 2`` (s): ``S_r + S_s = v_r * robot_time_s``."""
        return self.t_reaction_s + self.t_stop_s / 2


def forecast_clearance(
    v_robot_mps: float | np.ndarray,
    margin_m: float | np.ndarray,
    params: SSMParams,
    *,
    w_top_radps: float | np.ndarray,
    stopping: StoppingModel = UR5E_STOP,
) -> float | np.ndarray:
    """The separation (m) the planner requires from a *forecast* pose whose error margin is ``margin_m``,
    of a robot whose fastest point moves at ``v_robot_mps`` and fastest joint at ``w_top_radps``.

    ``S_r + S_s + C + Z_r + max(Z_d, margin)``: the forecast replaces ``S_h``, and its margin (the error
    of tracking plus prediction at that horizon, see :class:`app.prediction.forecast.HumanForecast`) takes
    the place of the sensing uncertainty ``Z_d`` where it is larger (both describe where the person may be
    instead of where they are reported; adding them would count the tracking error twice). ``S_r = v T_r``
    and ``S_s`` is the one stopping model's (:mod:`app.safety.stopping`, the governor's and the ground-truth
    monitor's): the robot stops in ``T_s = max(v / decel, w / joint decel)`` (a robot moving its joints at
    half their limit needs about 0.5 s, one creeping a few hundredths), and ``v`` covers ``v T_s / 2`` of
    it. ``params.t_stop_s`` (the constant-speed law's ``T_s``) does not enter. Element-wise.
    """
    v = np.maximum(v_robot_mps, 0.0)
    t_s = stopping.stop_time_s(v, w_top_radps)
    out = (
        v * params.t_reaction_s
        + stopping.stop_distance_m(v, t_s)
        + params.intrusion_m
        + params.z_robot_m
        + np.maximum(params.z_human_m, np.asarray(margin_m, dtype=np.float64))
    )
    return float(out) if np.ndim(out) == 0 else out


def required_separation(
    v_human_mps: float | np.ndarray,
    v_robot_mps: float | np.ndarray,
    *,
    t_reaction_s: float,
    t_stop_s: float | np.ndarray,
    constant_m: float,
    stop_distance_m: float | np.ndarray | None = None,
) -> float | np.ndarray:
    """ISO/TS 15066's protective separation ``S_p`` (m) with directed speeds, the one formula of the cell:
    ``v_h (T_r + T_s) + v_r T_r + S_s + constant``.

    The speed governor's envelope (its compiled twin, ``app.safety._kernels._sp``, which the tests compare
    with this), the ground-truth monitor and :func:`protective_separation` all compute it here.

    Args:
        v_human_mps: The person's speed toward the robot part (m/s); negative counts as 0.
        v_robot_mps: The robot part's speed toward the person (m/s); negative counts as 0.
        t_reaction_s: ``T_r`` (s).
        t_stop_s: ``T_s``, the robot's stopping time (s).
        constant_m: ``C + Z_d + Z_r`` (the monitor, which sees the true person: ``C + Z_r``) (m).
        stop_distance_m: ``S_s`` (m) from a stopping model; default ``v_r T_s / 2`` (a constant deceleration).

    Element-wise (arrays broadcast); a float for scalar arguments.
    """
    v_h = np.maximum(v_human_mps, 0.0)
    v_r = np.maximum(v_robot_mps, 0.0)
    s_s = v_r * (0.5 * np.asarray(t_stop_s)) if stop_distance_m is None else stop_distance_m
    out = v_h * (t_reaction_s + t_stop_s) + (v_r * t_reaction_s + s_s + constant_m)
    return float(out) if np.ndim(out) == 0 else out


def protective_separation(
    v_robot_mps: float | np.ndarray, params: SSMParams, *, v_human_mps: float | None = None
) -> float | np.ndarray:
    """ISO/TS 15066 protective separation distance ``S_p`` (m) for a robot speed ``v_robot_mps`` (m/s), with
    the fixed ``T_r`` and ``T_s`` of ``params`` (:func:`required_separation`).

    Args:
        v_robot_mps: Robot speed toward the person (m/s); negative values count as 0. Scalar or array.
        params: The SSM parameters.
        v_human_mps: The person's speed (m/s) when it is measured; default ``params.v_human_mps``.
    """
    return required_separation(
        params.v_human_mps if v_human_mps is None else v_human_mps,
        v_robot_mps,
        t_reaction_s=params.t_reaction_s,
        t_stop_s=params.t_stop_s,
        constant_m=params.constant_m,
    )


def max_safe_speed(
    separation_m: float | np.ndarray, params: SSMParams, *, v_human_mps: float | np.ndarray | None = None
) -> float | np.ndarray:
    """The largest robot speed (m/s) whose ``S_p`` fits into ``separation_m``: the speed-scaling law.

    Solves ``S_p(v) = separation_m`` for ``v``: ``v = (d - S_h - C - Z_d - Z_r) / (T_r + T_s / 2)``,
    clipped at 0 (the robot must stand still when the person is within ``S_p(0)``).
    """
    d = np.asarray(separation_m, dtype=np.float64)
    v_h = params.v_human_mps if v_human_mps is None else np.asarray(v_human_mps, dtype=np.float64)
    slack = d - v_h * (params.t_reaction_s + params.t_stop_s) - params.constant_m
    out = np.maximum(slack, 0.0) / params.robot_time_s
    return float(out) if out.ndim == 0 else out


def speed_scale(
    separation_m: float | np.ndarray,
    v_nominal_mps: float | np.ndarray,
    params: SSMParams,
    *,
    v_human_mps: float | np.ndarray | None = None,
) -> float | np.ndarray:
    """Fraction in [0, 1] of the nominal speed that keeps ``S_p`` within ``separation_m``.

    Args:
        separation_m: Current surface-to-surface distance robot-person (m); +inf when nobody is seen.
        v_nominal_mps: The speed (m/s) the robot would move at with scale 1 (e.g. its current TCP speed).
        params: The SSM parameters.
        v_human_mps: The person's measured speed (m/s), if any.

    Scalars give a float; arrays (e.g. one entry per robot part) broadcast and give an array.
    """
    d = np.asarray(separation_m, dtype=np.float64)
    v_nom = np.asarray(v_nominal_mps, dtype=np.float64)
    v_h = params.v_human_mps
    if v_human_mps is not None:
        v_h = np.maximum(np.asarray(v_human_mps, dtype=np.float64), 0.0)
    with np.errstate(invalid="ignore"):
        slack = d - v_h * (params.t_reaction_s + params.t_stop_s) - params.constant_m
    v_max = np.maximum(slack, 0.0) / params.robot_time_s
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.minimum(1.0, v_max / np.maximum(v_nom, 1e-300))
    out = np.where(v_nom <= 1e-9, np.where(v_max > 0.0, 1.0, 0.0), ratio)
    out = np.where(np.isfinite(d), out, np.where(d > 0, 1.0, 0.0))
    return float(out) if out.ndim == 0 else out
