"""The path speed scale's ramp: how fast the supervisor may raise the scale of the plan in execution.

The scale multiplies the plan's joint velocities; raising it accelerates the arm on top of the plan's own
acceleration. :func:`up_rate` bounds the ramp (no faster than a brake may lower the scale, nor than the
joints may speed up at the window's speeds), :func:`jump_scale` lets a plan that sets off from rest start at
any scale the ramp's velocity steps allow, and :func:`ramp_distance` is the fastest progress along the path
that the ramp allows (the supervisor's branch points). :class:`CreepWatch` says when a plan has crept
long enough at a low scale for the supervisor to weigh a backup that may arrive earlier.
"""

from __future__ import annotations

import math

import numpy as np

from app.control.trajectory_views import SpeedProfile, TrajectoryLike, traj_state

__all__ = ["CreepWatch", "jump_scale", "ramp_distance", "up_rate"]


def up_rate(scale_up_rate: float, brake_rate_per_s: float, joint_accel: float, w_top_radps: float) -> float:
    """How fast (1/s) the path scale may rise: the ramp, no faster than a brake may lower it nor than the
    joints may speed up (``joint_accel`` for the fastest joint at ``w_top_radps`` at scale 1), so that the arm
    follows its command (a joint at 1.9 rad/s ramped at 4/s would need 7.6 rad/s^2, lag, then overshoot)."""
    up = min(scale_up_rate, brake_rate_per_s) if math.isfinite(brake_rate_per_s) else scale_up_rate
    if w_top_radps > 1e-9:
        up = min(up, joint_accel / w_top_radps)
    return up


def jump_scale(
    s: float, up_rate_per_s: float, dt: float, traj: TrajectoryLike, profile: SpeedProfile, tau: float
) -> float:
    """The largest path scale one servo tick of ``dt`` can reach from ``s`` on the plan ``traj`` (its speed
    profile ``profile``) at path time ``tau``: the ramp's ``s + up_rate_per_s dt``, or higher where the path
    itself is slower than over the window ahead (a plan setting off from rest): any scale at which no joint's
    velocity and no part's speed changes by more than the ramp may change them at the window's speeds.
    Without it a plan from rest would accelerate twice over, along its own profile and with the scale's ramp
    from 0 (0.12 s lost on every short leg at full speed, measured on seeds 1000-1009)."""
    hi = s + up_rate_per_s * dt
    if hi >= 1.0 or dt <= 0.0:
        return min(hi, 1.0)
    w_now = float(np.max(np.abs(traj_state(traj, tau)[1])))
    v_now = float(profile.speed_at(tau).max())
    room = min(
        profile.top_joint_window_at(tau) / w_now if w_now > 1e-12 else math.inf,
        float(profile.window_at(tau).max()) / v_now if v_now > 1e-12 else math.inf,
    )
    return min(max(hi, up_rate_per_s * dt * room), 1.0)


def ramp_distance(s: float, up_rate_per_s: float, horizon_s: float) -> float:
    """Path-time distance covered in ``horizon_s`` starting at scale ``s`` and ramping up at
    ``up_rate_per_s`` to 1 (the fastest the robot can progress)."""
    if s >= 1.0:
        return horizon_s
    t_full = (1.0 - s) / up_rate_per_s if up_rate_per_s > 0 else math.inf
    if t_full >= horizon_s:
        return s * horizon_s + 0.5 * up_rate_per_s * horizon_s**2
    return s * t_full + 0.5 * up_rate_per_s * t_full**2 + (horizon_s - t_full)


class CreepWatch:
    """When the plan in execution has crept below ``scale`` for ``after_s`` (s): :meth:`due` is True then,
    and again every ``after_s`` while it keeps creeping (``scale`` None: never)."""

    def __init__(self, scale: float | None, after_s: float) -> None:
        self.scale, self.after_s = scale, float(after_s)
        self._plan = -1  # the plan whose creeping is being timed, and since when (s)
        self._since = 0.0

    def due(self, t: float, s: float, plan_id: int) -> bool:
        """The plan ``plan_id`` runs at scale ``s`` at time ``t``: has it crept long enough?"""
        if self.scale is None:
            return False
        if s >= self.scale or plan_id != self._plan:
            self._plan, self._since = plan_id, t
            return False
        if t - self._since < self.after_s:
            return False
        self._since = t
        return True


class StillWatch:
    """Since when a robot with somewhere to go has (nearly) stood still: crept along its plans at a mean path
    scale of at most ``scale``, less ``slack_s`` of path time in all (a robot the governor holds at the edge
    of ``S_p`` creeps on by a few per cent now and then)."""

    def __init__(self, t0: float, *, scale: float = 0.05, slack_s: float = 0.05) -> None:
        self.scale, self.slack_s = float(scale), float(slack_s)
        self.since = float(t0)
        self._crept = 0.0  # path time covered since then (s)

    def tick(self, t: float, s: float, dt: float, *, waiting: bool) -> None:
        """A servo tick to ``t`` at path scale ``s`` over ``dt``; ``waiting``: the robot has nowhere to go
        yet (no goal, or the gripper's dwell), which is not standing still."""
        self._crept += s * dt
        if waiting or self._crept > self.scale * (t - self.since) + self.slack_s:
            self.reset(t)

    def reset(self, t: float) -> None:
        self.since, self._crept = float(t), 0.0

    def still_for(self, t: float) -> float:
        """How long (s) the robot has stood still at ``t``."""
        return max(float(t) - self.since, 0.0)
