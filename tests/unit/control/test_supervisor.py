"""The replan state machine with small fakes: a point robot (q[:3] is its position), a straight-line planner
that detours sideways when the forecast blocks the line, and a "point person" (all joints at one point).

Time is driven by hand (no clock, no sleeps): servo ticks at 100 Hz and frames at 30 Hz.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from governor_reference import governed_scale_reference

from app.control.backup import BackupComputer, InlinePlanJobs
from app.control.scale_ramp import ramp_distance
from app.control.supervisor import Supervisor, SupervisorConfig
from app.control.trajectory_views import HoldTrajectory, ScaledView, SpeedProfile
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS, HumanFrame
from app.safety.governor import (
    PartSeparation,
    PathClosing,
    SeparationModel,
    SpeedScaleLaw,
    ssm_alone,
)
from app.safety.ssm import SSMParams

R_HUMAN = 0.1  # radius of the point person (m)
CLEAR = 0.5  # clearance the fake planner requires (m)
SPEED = 0.5  # fake plan speed (m/s)
FAR = np.array([10.0, 0.0, 0.0])
#: S_p = 0.1 m + v_h (0.1 s + T_s) + v_r (0.1 s + T_s / 2), T_s the supervisor's brake (its default, the
#: UR5e's stopping model; ``sp`` and ``max_speed`` of a robot moving as one part: v_r / (2 m/s^2)); a person
#: speeds up at most at 8 m/s^2, up to 2 m/s
SSM = SeparationModel(
    s0_m=0.1, t_reaction_s=0.1, stop_decel_mps2=2.0, human_speed_max_mps=2.0, human_accel_mps2=8.0
)


#: the ISO/TS 15066 speed-scaling law with T_r = 0.1 s, T_s = 0.1 s, C + Z_d + Z_r = 0.1 m
LAW = SpeedScaleLaw(
    SSMParams(t_reaction_s=0.1, t_stop_s=0.1, intrusion_m=0.05, z_human_m=0.04, z_robot_m=0.01)
)


def person_at(p: np.ndarray) -> np.ndarray:
    return np.tile(np.asarray(p, dtype=float), (NUM_JOINTS, 1))


def q_of(p: np.ndarray) -> np.ndarray:
    q = np.zeros(6)
    q[:3] = p
    return q


class LinearTrajectory:
    """Piecewise-linear joint trajectory through (times, q); holds the ends."""

    def __init__(self, times: np.ndarray, q: np.ndarray) -> None:
        self.times = np.asarray(times, dtype=float)
        self.qs = np.asarray(q, dtype=float)

    @property
    def t_start(self) -> float:
        return float(self.times[0])

    @property
    def t_end(self) -> float:
        return float(self.times[-1])

    def q(self, t: Any) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        out = np.stack([np.interp(t, self.times, self.qs[:, j]) for j in range(6)], axis=-1)
        return out

    def sample(self, dt_s: float, *, t_from: float, t_to: float) -> np.ndarray:
        return np.linspace(t_from, t_to, max(math.ceil((t_to - t_from) / dt_s), 1) + 1)

    def shifted(self, dt_s: float) -> LinearTrajectory:
        return type(self)(self.times + dt_s, self.qs)

    def qd(self, t: Any) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        tt = np.atleast_1d(t)
        if self.times.shape[0] < 2:
            return np.zeros((*t.shape, 6))
        idx = np.clip(np.searchsorted(self.times, tt, side="right") - 1, 0, self.times.shape[0] - 2)
        dts = np.diff(self.times)
        slope = np.diff(self.qs, axis=0) / np.where(dts > 0, dts, 1.0)[:, None]
        v = slope[idx]
        v[(tt < self.times[0]) | (tt >= self.times[-1])] = 0.0
        return v.reshape(*t.shape, 6)


@dataclass
class FakePlan:
    times: np.ndarray
    q: np.ndarray
    nodes: np.ndarray


@dataclass
class FakeResult:
    ok: bool
    plan: Any
    reason: str
    expanded: int = 0
    compute_s: float = 0.0
    blocked: str | None = None


class PointGeometry:
    """The point robot as one part."""

    def part_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        return np.min(np.linalg.norm(np.asarray(joints) - q[:3], axis=-1), axis=-1)[:, None] - R_HUMAN

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(qd)[..., :3], axis=-1).reshape(-1, 1)

    def path_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(np.asarray(joints)[None] - np.asarray(q)[:, None, :3], axis=-1)
        return d.min(axis=1)[:, None] - R_HUMAN

    def separation(self, q: np.ndarray, joints: np.ndarray) -> float:
        return float(self.part_separations(q, np.asarray(joints)[None])[0, 0])

    def near_person(self, q, joints, joints_before, dt_s, *, band_m):
        sep = self.part_separations(q, np.asarray(joints)[None])[0]
        v = float(np.max(np.linalg.norm(np.asarray(joints) - np.asarray(joints_before), axis=-1))) / dt_s
        return sep, np.array([v])


def make_traj(plan: FakePlan, qd0: np.ndarray | None) -> LinearTrajectory:
    return LinearTrajectory(plan.times, plan.q)


class FakePlanner:
    """Straight line at SPEED; when the forecast blocks it, a detour: sideways, across, back."""

    def __init__(self, goals: dict[str, np.ndarray]) -> None:
        self.goals = goals
        self.plan_calls = 0
        self.emergency_calls = 0
        self.raise_after: int | None = None
        self.detour_y = 1.0
        self.returned: list[LinearTrajectory] = []

    def _line(self, pts: list[np.ndarray], t0: float) -> FakePlan:
        times = [t0]
        for a, b in itertools.pairwise(pts):
            times.append(times[-1] + max(np.linalg.norm(b - a) / SPEED, 1e-3))
        return FakePlan(np.array(times), np.stack([q_of(p) for p in pts]), np.arange(len(pts)))

    def _violates(self, plan: FakePlan, forecast: HumanForecast | None) -> bool:
        if forecast is None:
            return False
        traj = LinearTrajectory(plan.times, plan.q)
        return (
            self.first_violation(traj, forecast, t_from=traj.t_start, t_to=traj.t_end, dt_s=0.02) is not None
        )

    def plan(self, *, q_start, t_start, goal, forecast, workers=1, deadline_s=None, qd0=None) -> FakeResult:
        self.plan_calls += 1
        if self.raise_after is not None and self.plan_calls > self.raise_after:
            raise RuntimeError("planner crashed (test)")
        a = np.asarray(q_start)[:3]
        b = self.goals[goal]
        side = np.array([0.0, self.detour_y, 0.0])
        for pts in ([a, b], [a, a + side, b + side, b]):
            p = self._line(pts, t_start)
            if not self._violates(p, forecast):
                return FakeResult(True, p, "ok")
        return FakeResult(False, None, "blocked")

    def emergency(self, *, q_start, t_start, forecast, horizon_s) -> FakeResult:
        self.emergency_calls += 1
        q = np.asarray(q_start)
        return FakeResult(
            True, FakePlan(np.array([t_start, t_start + horizon_s]), np.stack([q, q]), np.zeros(2)), ""
        )

    def predicted_check(self, traj, forecast, *, timing=None) -> tuple[float | None, float]:
        return self.first_violation(traj, forecast, t_from=traj.t_start, t_to=traj.t_end + 0.3), traj.t_end

    def first_violation(self, traj, forecast, *, t_from, t_to, dt_s=None) -> float | None:
        ts = traj.sample(dt_s or 0.02, t_from=t_from, t_to=t_to)
        q = traj.q(ts)
        joints, margins = forecast.poses_at(ts)
        d = np.min(np.linalg.norm(joints - q[:, None, :3], axis=-1), axis=1) - R_HUMAN - margins
        bad = np.nonzero(d < CLEAR)[0]
        return float(ts[bad[0]]) if bad.size else None


PersonFn = Callable[[float], np.ndarray]


class Harness:
    """Drives a supervisor with servo ticks at 100 Hz and frames at 30 Hz."""

    def __init__(
        self,
        person: PersonFn,
        *,
        forecast_fn: Callable[[float], HumanForecast] | None = None,
        fixed_compute_s: float | None = 0.01,
        q0: np.ndarray | None = None,
        goals: dict[str, np.ndarray] | None = None,
        config: SupervisorConfig | None = None,
        candidate: bool = False,
        timing: Any = None,
    ) -> None:
        self.candidate = candidate  # weigh the reactive method's plan (the person held still) at each backup
        self.goals = goals or {"B": np.array([2.0, 0.0, 0.0])}
        self.planner = FakePlanner(self.goals)
        self.geometry = PointGeometry()
        self.config = config or SupervisorConfig(deadline_s=0.1, frame_period_s=1 / 30)
        computer = BackupComputer(
            self.planner, make_traj, self.geometry, deadline_s=self.config.deadline_s, workers=1
        )
        self.jobs = InlinePlanJobs(computer, fixed_compute_s=fixed_compute_s)
        self.events: list[tuple[float, str, dict]] = []
        self.sup = Supervisor(
            planner=self.planner,
            geometry=self.geometry,
            jobs=self.jobs,
            make_trajectory=make_traj,
            separation=SSM,
            speed_scale=LAW,
            config=self.config,
            q0=np.zeros(6) if q0 is None else q0,
            t0=0.0,
            on_event=lambda t, k, p: self.events.append((t, k, p)),
            timer=_FakeTimer(),
            timing=timing,
        )
        self.person = person
        self.forecast_fn = forecast_fn
        self.t = 0.0
        self.dt = 0.01
        self.next_frame = 0.0
        self.frames_on = True
        self.log: list[tuple[float, np.ndarray, float, float]] = []  # t, q, scale, v
        self.decisions: list[Any] = []
        self.sup.begin(0.0)

    def forecast(self, t: float) -> HumanForecast:
        if self.forecast_fn is not None:
            return self.forecast_fn(t)
        return HumanForecast.hold(HumanFrame(t, self.person(t)))

    def run(self, until: float) -> None:
        prev_q = None
        while self.t < until - 1e-9:
            t = self.t
            if self.frames_on and t >= self.next_frame - 1e-9:
                frame = HumanFrame(t, self.person(t))
                held = HumanForecast.hold(frame) if self.candidate else None
                self.decisions.append(self.sup.on_frame(frame, self.forecast(t), t_now=t, candidate=held))
                self.next_frame += self.config.frame_period_s
            elif not self.frames_on:
                self.next_frame = t
            cmd = self.sup.servo(t)
            v = 0.0 if prev_q is None else float(np.linalg.norm(cmd.q[:3] - prev_q[:3]) / self.dt)
            self.log.append((t, cmd.q.copy(), cmd.scale, v))
            prev_q = cmd.q
            self.t = round(t + self.dt, 9)

    def kinds(self) -> list[str]:
        return [k for _, k, _ in self.events]


class _FakeTimer:
    """A timer that advances 1 ms per call (compute times are deterministic)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        self.t += 0.001
        return self.t


def _monitor_violations(h: Harness) -> int:
    """Ticks where the moving robot is closer to the true person than S_p of its speed and of the person's
    directed speed toward it (independent of the supervisor: true poses, finite differences)."""
    bad = 0
    for k in range(1, len(h.log)):
        t, q, _, v = h.log[k]
        if v <= 1e-3:
            continue
        d = h.geometry.separation(q, h.person(t))
        d_before = h.geometry.separation(q, h.person(t - h.dt))
        v_h = max((d_before - d) / h.dt, 0.0)
        # stopping time from v with the supervisor's brake (the point robot's joint speed is its speed)
        t_s = max(v / h.config.brake_decel_mps2, v / h.config.brake_joint_decel)
        need = 0.1 + v_h * (0.1 + t_s) + v * (0.1 + t_s / 2)
        if d < need - 1e-9:
            bad += 1
    return bad


# ----------------------------------------------------------------------------------------------------------


def test_reaches_goal_when_nobody_is_near() -> None:
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(5.0)
    assert h.sup.take_arrival() == "B"
    np.testing.assert_allclose(h.log[-1][1][:3], [2.0, 0.0, 0.0], atol=1e-9)
    c = h.sup.counters
    assert c.stop_replans == 0 and c.online_replans == 0 and c.deadline_misses == 0
    # the robot starts moving once the first plan is ready: its compute time (10 ms) after the first frame
    first_move = next(t for t, q, _, _ in h.log if q[0] > 0)
    assert first_move >= 0.01 - 1e-9
    # under way from the first move to the arrival, at full speed but for the ramp up
    last_move = next(t for t, q, _, _ in reversed(h.log) if abs(q[0] - 2.0) > 1e-9)
    assert c.moving_time_s == pytest.approx(last_move - first_move, abs=0.05)
    assert 0.9 < c.scale_time_s / c.moving_time_s <= 1.0


def test_the_scale_rises_no_faster_than_a_brake_may_lower_it() -> None:
    """The arm's joints accelerate within their limits: a scale ramped faster than the stopping model's
    deceleration allows would leave the arm lagging its command, then overshooting it at the next brake."""
    config = SupervisorConfig(
        deadline_s=0.1, frame_period_s=1 / 30, brake_decel_mps2=1.0, brake_joint_decel=1.0, scale_up_rate=4.0
    )
    h = Harness(lambda t: person_at(FAR), config=config)
    h.sup.set_goal("B")
    h.run(5.0)
    assert h.sup.take_arrival() == "B"
    scales = np.array([s for _, _, s, _ in h.log])
    rate = 1.0 / SPEED  # the path's 0.5 m/s braked at 1 m/s^2 and 1 rad/s^2: the scale falls at 2/s at most
    assert np.max(np.diff(scales)) <= rate * h.dt + 1e-9
    assert np.max(np.diff(scales)) == pytest.approx(rate * h.dt)  # and rises at that rate from rest
    # the default (a brake at 3 m/s^2 and 3 rad/s^2 of the 0.5 m/s path: 6/s) leaves the ramp's 4/s
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(5.0)
    assert np.max(np.diff([s for _, _, s, _ in h.log])) == pytest.approx(4.0 * h.dt)


class EasedTrajectory(LinearTrajectory):
    """Through (times, q) at rest at every waypoint (a cubic ease per segment): a plan setting off from
    rest, as the planner's fitted trajectories do."""

    def _segment(self, t: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        tt = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, tt, side="right") - 1, 0, self.times.shape[0] - 2)
        h = self.times[i + 1] - self.times[i]
        return i, np.clip((tt - self.times[i]) / h, 0.0, 1.0), h, self.qs[i + 1] - self.qs[i]

    def q(self, t: Any) -> np.ndarray:
        i, u, _, dq = self._segment(t)
        out = self.qs[i] + dq * (3 * u**2 - 2 * u**3)[:, None]
        return out.reshape(*np.shape(t), 6)

    def qd(self, t: Any) -> np.ndarray:
        _, u, h, dq = self._segment(t)
        return (dq * ((6 * u - 6 * u**2) / h)[:, None]).reshape(*np.shape(t), 6)


def test_a_plan_from_rest_sets_off_at_the_governed_scale_without_a_second_ramp(monkeypatch) -> None:
    """A plan that starts at rest accelerates along its own profile: the scale need not ramp up from 0 on
    top of it (that would arrive late by half the ramp's time on every leg), while a plan that starts at
    speed still gets the ramp (:func:`test_the_scale_rises_no_faster_than_a_brake_may_lower_it`)."""
    monkeypatch.setattr(
        sys.modules[__name__], "make_traj", lambda plan, qd0: EasedTrajectory(plan.times, plan.q)
    )
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(6.0)
    assert h.sup.take_arrival() == "B"
    t = np.array([r[0] for r in h.log])
    q = np.stack([r[1] for r in h.log])[:, 0]
    scales = np.array([r[2] for r in h.log])
    under_way = np.flatnonzero(q > 1e-12)
    first = under_way[0]
    assert scales[first] == pytest.approx(1.0)  # the first tick under way is at full scale, no ramp from 0
    t_dep = t[first - 1]
    t_arr = t[np.flatnonzero(q >= 2.0 - 1e-9)[0]]
    assert t_arr - t_dep == pytest.approx(2.0 / SPEED, abs=2 * h.dt)  # the plan's own duration, on time
    v = np.diff(q) / h.dt
    assert np.max(np.abs(np.diff(v))) <= 6 * 2.0 / (2.0 / SPEED) ** 2 * h.dt + 1e-6  # its own acceleration


@pytest.mark.parametrize("faster", [True, False])
def test_a_creeping_plan_is_replaced_by_a_backup_only_where_it_arrives_earlier(
    monkeypatch, faster: bool
) -> None:
    """A plan that the governor holds below ``creep_scale`` is weighed against a backup from its branch
    point at the predicted timing (here: the fake planner's, and a stub for the rest of the creeping plan):
    the backup is executed where it arrives ``creep_gain_s`` earlier, else the plan in execution goes on."""
    import app.control.supervisor as sup_mod

    config = SupervisorConfig(deadline_s=0.1, frame_period_s=1 / 30, creep_scale=0.2, creep_after_s=0.3)
    h = Harness(lambda t: person_at(FAR), config=config, timing=object())
    # the governor holds the robot at a creep; the backup from the branch point is predicted to arrive at its
    # own full-speed end, the rest of the creeping plan 5 s after (faster) or before (not) that
    monkeypatch.setattr(Supervisor, "_governed_scale", lambda self, *a: 0.05)
    offset = 5.0 if faster else -5.0
    monkeypatch.setattr(sup_mod, "predicted_arrival_from", lambda traj, tau_b, t_b, *a: t_b + 4.0 + offset)
    plan = h.planner.plan

    def with_arrival(**kw):
        res = plan(**kw)
        if res.ok:
            res.arrival_s = float(res.plan.times[-1])
        return res

    monkeypatch.setattr(h.planner, "plan", with_arrival)
    h.sup.set_goal("B")
    h.run(3.0)
    assert h.sup.counters.improvements > 0 if faster else h.sup.counters.improvements == 0
    kinds = [d.action for d in h.decisions]
    assert "improve" in kinds  # weighed in both cases, at most once per creep_after_s
    assert kinds.count("improve") <= 3.0 / config.creep_after_s + 1
    # no creeping, no weighing: the same scene at full speed
    h2 = Harness(lambda t: person_at(FAR), config=config, timing=object())
    monkeypatch.undo()
    h2.sup.set_goal("B")
    h2.run(3.0)
    assert "improve" not in [d.action for d in h2.decisions]


def test_hold_and_scaled_view() -> None:
    hold = HoldTrajectory(np.arange(6.0), 2.0)
    assert hold.q(np.array([0.0, 5.0])).shape == (2, 6)
    assert hold.t_end == 2.0 and not np.any(hold.qd(3.0))
    lin = LinearTrajectory(np.array([0.0, 2.0]), np.stack([q_of([0, 0, 0]), q_of([2, 0, 0])]))
    view = ScaledView(lin, t_ref=10.0, tau_ref=1.0, scale=0.5)
    assert view.t_start == 10.0 and view.t_end == pytest.approx(12.0)
    assert view.q(11.0)[0] == pytest.approx(1.5)
    assert view.qd(11.0)[0] == pytest.approx(0.5)


def testramp_distance() -> None:
    assert ramp_distance(1.0, 4.0, 0.1) == pytest.approx(0.1)
    assert ramp_distance(0.0, 4.0, 0.1) == pytest.approx(0.02)  # 0.5 * 4 * 0.01
    assert ramp_distance(0.9, 4.0, 0.1) == pytest.approx(0.9 * 0.025 + 0.5 * 4 * 0.025**2 + 0.075)


def test_speed_profile_windows() -> None:
    lin = LinearTrajectory(
        np.array([0.0, 1.0, 2.0]), np.stack([q_of([0, 0, 0]), q_of([1, 0, 0]), q_of([1, 0, 0])])
    )
    prof = SpeedProfile.of(lin, PointGeometry(), step_s=0.1, window_s=0.3)
    assert prof.window_at(0.0)[0] == pytest.approx(1.0)
    assert prof.window_at(0.75)[0] == pytest.approx(1.0)  # the fast part is still within the window
    assert prof.window_at(1.5)[0] == pytest.approx(0.0)
    assert prof.window_at(5.0)[0] == 0.0
    assert prof.speed_at(0.5)[0] == pytest.approx(1.0) and prof.speed_at(1.5)[0] == pytest.approx(0.0)


def walker(start: np.ndarray, end: np.ndarray, t0: float, t1: float) -> PersonFn:
    """A person walking at constant speed from ``start`` (until ``t0``) to ``end`` (from ``t1`` on)."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)

    def person(t: float) -> np.ndarray:
        u = float(np.clip((t - t0) / (t1 - t0), 0.0, 1.0))
        return person_at(start + u * (end - start))

    return person


def perfect_forecast(person: PersonFn, known_from: float) -> Callable[[float], HumanForecast]:
    """The person's true future over 1.5 s; before ``known_from`` the current pose held."""

    def fc(t: float) -> HumanForecast:
        if t < known_from:
            return HumanForecast.hold(HumanFrame(t, person(t)))
        times = t + np.linspace(0.0, 1.5, 16)
        joints = np.stack([person(float(x)) for x in times])
        return HumanForecast(t0=t, times=times, joints=joints, margins=np.zeros(16))

    return fc


# the person walks slowly onto the straight path at x = 1.0, arriving at t = 3.4
WHERE = np.array([1.0, 0.0, 0.0])
WALK_IN = walker(np.array([1.0, -1.0, 0.0]), WHERE, 0.4, 3.7)


def test_late_predicted_violation_switches_to_the_backup_online() -> None:
    h = Harness(WALK_IN, forecast_fn=perfect_forecast(WALK_IN, 0.5))
    h.sup.set_goal("B")
    h.run(10.0)
    c = h.sup.counters
    assert c.online_replans >= 1
    assert c.stop_replans == 0
    assert "online_replan" in h.kinds()
    # it went around: the executed path left the straight line
    assert max(q[1] for _, q, _, _ in h.log) > 0.3
    assert h.sup.take_arrival() == "B"
    assert _monitor_violations(h) == 0


def test_a_switch_the_robot_is_held_short_of_gives_way_to_a_new_backup(monkeypatch) -> None:
    """An online replan branches from where the fastest ramp would bring the robot at ``T + D``; where the
    governor holds the robot short of that branch point (someone near), the switch can never happen, and while
    it is pending no frame plans another backup. Once it is overdue (``D`` past its time) with the robot held
    still it gives way: the next frame decides afresh from where the robot is (a study trial stood 20 s on
    such a switch). A creeping robot keeps its switch (it gets there late, as a switch may)."""
    h = Harness(WALK_IN, forecast_fn=perfect_forecast(WALK_IN, 0.5))
    h.sup.set_goal("B")
    while h.t < 10.0 and not (h.sup._pending is not None and h.sup._pending.reason == "online_replan"):
        h.run(h.t + h.dt)
    stuck = h.sup._pending
    assert stuck is not None, "the scenario should schedule an online replan"
    monkeypatch.setattr(h.sup, "_governed_scale", lambda *args: 0.0)  # held: never reaches the branch point
    h.run(stuck.t_switch + h.config.deadline_s + 3 * h.config.frame_period_s)
    assert h.sup._pending is not stuck
    assert h.sup.counters.online_replans == 0  # the held robot never took the switch
    after = [d.action for d in h.decisions[-2:]]
    assert set(after) & {"online_replan", "stop_replan", "hold"}, after


def test_imminent_violation_stops_and_takes_the_emergency_plan() -> None:
    """The forecast suddenly says the person will be on the path a few cm ahead of the robot within D (the
    true person stays far away, so only the decision reacts, not the speed governor)."""
    h_ref = Harness(lambda t: person_at(FAR))

    def fc(t: float) -> HumanForecast:
        if t < 1.0:
            return HumanForecast.hold(HumanFrame(t, person_at(FAR)))
        ahead = h_ref.sup.status().q[:3] + np.array([0.55, 0.0, 0.0])
        times = np.array([t, t + 0.05, t + 2.0])
        joints = np.stack([person_at(FAR), person_at(ahead), person_at(ahead)])
        return HumanForecast(t0=t, times=times, joints=joints, margins=np.zeros(3))

    h = h_ref
    h.forecast_fn = fc
    h.sup.set_goal("B")
    h.run(1.0)
    assert h.sup.counters.stop_replans == 0
    h.run(2.0)
    c = h.sup.counters
    assert c.stop_replans == 1
    assert c.emergency_plans == 1
    ev = next(p for _, k, p in h.events if k == "stop_replan")
    assert ev["reason"] == "predicted_violation" and ev["violation_t"] <= 1.0 + h.config.deadline_s
    assert ev["scale"] == pytest.approx(1.0)  # under way at full speed (nobody near) when it stopped
    assert c.stop_replans_moving == 1
    # braking starts at once and never speeds up until the robot is at rest
    speeds = [v for t, _, _, v in h.log if 1.01 <= t <= 1.5]
    k_rest = next(i for i, v in enumerate(speeds) if v < 1e-9)
    assert k_rest > 0
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(speeds[: k_rest + 1]))
    assert h.sup.status().state in ("stopped", "collision_avoidance")


def test_stop_distance_violation_stops_the_robot() -> None:
    # a person suddenly right next to the path: within S_p(0) of the robot
    # (the forecast misses the person, so only the measured separation can stop the robot)
    person = walker(np.array([0.5, 1.5, 0.0]), np.array([0.5, 0.12, 0.0]), 0.2, 1.0)
    h = Harness(person, forecast_fn=lambda t: HumanForecast.hold(HumanFrame(t, person_at(FAR))))
    h.sup.set_goal("B")
    h.run(1.5)
    assert h.sup.counters.stop_replans >= 1
    ev = [p for _, k, p in h.events if k == "stop_replan"]
    assert any(p["reason"] == "stop_distance" for p in ev)
    t_stop, stop = next((t, p) for t, k, p in h.events if k == "stop_replan")
    assert min(v for t, _, _, v in h.log if t_stop <= t <= t_stop + 0.2) < 1e-9  # braked to rest
    # the event says how fast the robot went along its path when stopped (the scale of the last tick; here
    # the governor had already slowed it to rest as the person came near)
    scale_before = [s for t, _, s, _ in h.log if t < t_stop][-1]
    assert stop["scale"] == pytest.approx(scale_before, abs=1e-4)
    moving = sum(1 for _, k, p in h.events if k == "stop_replan" and p["scale"] > 1e-3)
    assert h.sup.counters.stop_replans_moving == moving < h.sup.counters.stop_replans
    assert _monitor_violations(h) == 0


def test_backup_is_rechecked_against_the_latest_forecast_before_the_switch() -> None:
    """A backup planned against an older forecast is not executed when the newest forecast says it
    collides soon: the switch takes the emergency path instead."""
    base = perfect_forecast(WALK_IN, 0.5)
    state: dict[str, Any] = {"after": None, "h": None}

    def fc(t: float) -> HumanForecast:
        after = state["after"]
        if after is not None and t > after + 1e-9:
            # the frames after the one that scheduled the switch see someone right where the detour begins
            p = state["h"].sup.status().q[:3] + np.array([0.0, 0.62, 0.0])
            times = np.array([t, t + 3.0])
            return HumanForecast(t0=t, times=times, joints=np.stack([person_at(p)] * 2), margins=np.zeros(2))
        return base(t)

    h = Harness(WALK_IN, forecast_fn=fc)
    state["h"] = h
    h.sup.set_goal("B")
    while not any(d.action == "online_replan" for d in h.decisions):
        h.run(h.t + 0.01)
        assert h.t < 3.0
    state["after"] = h.t - 0.01
    calls = h.planner.plan_calls
    h.run(h.t + 0.3)
    assert h.planner.plan_calls > calls  # the backup was computed...
    assert h.sup.counters.online_replans == 0  # ...but not executed
    assert any(k == "plan_failed" and "violates the latest forecast" in p["reason"] for _, k, p in h.events)
    assert h.sup.counters.stop_replans == 1
    assert max(abs(q[1]) for _, q, _, _ in h.log) < 1e-9  # never on the detour


@pytest.mark.parametrize("clear_start", [True, False])
def test_a_robot_at_rest_sets_off_only_on_a_plan_the_latest_forecast_leaves_clear(clear_start: bool) -> None:
    """The start plan is made against a forecast with nobody near; by the time it is ready the forecast has
    someone standing on its path, met well after T + D. With ``clear_start`` the robot stays at rest and its
    next plan goes around; without, it sets off on the straight plan (the paper's rule for backups: only a
    violation before T + D forbids the switch) and leaves it later by an online replan."""
    on_path = person_at(np.array([1.0, 0.0, 0.0]))

    def fc(t: float) -> HumanForecast:
        if t < 0.02:
            return HumanForecast.hold(HumanFrame(t, person_at(FAR)))
        return HumanForecast(
            t0=t, times=np.array([t, t + 3.0]), joints=np.stack([on_path] * 2), margins=np.zeros(2)
        )

    config = SupervisorConfig(deadline_s=0.1, frame_period_s=1 / 30, clear_start=clear_start)
    # (the start plan takes 50 ms: the next frame, whose forecast has the person on its path, comes first)
    h = Harness(lambda t: person_at(FAR), forecast_fn=fc, config=config, fixed_compute_s=0.05)
    h.sup.set_goal("B")
    h.run(12.0)
    moving = [q for _, q, _, v in h.log if v > 1e-6]
    first = moving[0]
    rejected = [
        t for t, k, p in h.events if k == "plan_failed" and "violates the latest forecast" in p["reason"]
    ]
    if clear_start:
        assert rejected and rejected[0] < 0.5
        assert abs(first[0]) < 1e-9 and first[1] > 0  # first motion: sideways, onto the detour
        assert h.sup.counters.online_replans == 0
    else:
        assert not rejected
        assert first[0] > 0 and abs(first[1]) < 1e-9  # first motion: straight at the person
        assert h.sup.counters.online_replans >= 1
    assert h.sup.counters.stop_replans == 0
    assert h.sup.take_arrival() == "B"
    assert _monitor_violations(h) == 0


@pytest.mark.parametrize("blocked", ["goal", "start", None])
def test_a_robot_at_rest_waits_for_the_person_apart_from_waiting_for_a_plan(blocked: str | None) -> None:
    """For the first second the planner finds no plan: the person in the way as forecast (its goal occupied,
    or the robot unable to leave), or for another reason (None). The time at rest counts as waiting for the
    person in the first cases, for a plan in the last; the plan computed before the first failure counts as
    waiting for a plan in all, and the plan that comes once the person has gone ends the wait."""
    h = Harness(lambda t: person_at(FAR))
    real = h.planner.plan

    def plan(**kw: Any) -> FakeResult:
        if h.t < 1.0:
            return FakeResult(False, None, "in the way (test)", blocked=blocked)
        return real(**kw)

    h.planner.plan = plan  # type: ignore[method-assign]
    h.sup.set_goal("B")
    h.run(6.0)
    assert h.sup.take_arrival() == "B"
    budget = h.sup.counters.budget_s
    assert sum(budget.values()) == pytest.approx(6.0, abs=0.02)
    waited = budget["waiting_for_person"] + budget["waiting_for_plan"]
    start_deadline = h.config.start_deadline
    assert 1.0 <= waited <= 1.0 + start_deadline + 0.1  # until the first plan after t = 1 s is due
    if blocked is None:
        assert budget["waiting_for_person"] == 0.0
    else:
        first_failure = next(t for t, k, _ in h.events if k == "plan_failed")
        assert budget["waiting_for_person"] >= 1.0 - first_failure - 0.02
        assert budget["waiting_for_plan"] <= first_failure + start_deadline + 0.02
    assert budget["moving_full"] + budget["moving_scaled"] > 0


@pytest.mark.parametrize("start_deadline_s", [None, 0.15])
def test_a_robot_at_rest_waits_its_start_deadline_for_the_first_plan(start_deadline_s: float | None) -> None:
    """Without ``start_when_ready`` the plan that sets a robot at rest moving is due at the start deadline
    (3 D unless the settings say otherwise, ``HRC_START_DEADLINE_S``): the robot waits that long for it, and
    the engine passes the settings through."""
    from app.config import Settings
    from app.control.engine import EngineOptions, supervisor_config

    settings = Settings(deadline_s=0.1, start_deadline_s=start_deadline_s, start_when_ready=False)
    engine_cfg = supervisor_config(settings, "proactive", EngineOptions())
    expected = 0.3 if start_deadline_s is None else start_deadline_s
    assert engine_cfg.start_deadline == pytest.approx(expected)
    assert not engine_cfg.start_when_ready
    assert supervisor_config(Settings(), "proactive", EngineOptions()).start_when_ready
    cfg = SupervisorConfig(
        deadline_s=0.1, frame_period_s=1 / 30, start_deadline_s=start_deadline_s, start_when_ready=False
    )
    h = Harness(lambda t: person_at(FAR), config=cfg)
    h.sup.set_goal("B")
    h.run(3.0)
    budget = h.sup.counters.budget_s
    assert budget["waiting_for_plan"] == pytest.approx(expected, abs=0.02)
    assert budget["moving_full"] + budget["moving_scaled"] > 0


def test_a_robot_at_rest_sets_off_as_soon_as_its_plan_is_ready() -> None:
    """The start deadline is the longest a robot at rest waits for its plan, not how long it always waits:
    the plan (10 ms of compute here) starts at the first servo tick after it is ready, timed from then."""
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(3.0)
    budget = h.sup.counters.budget_s
    assert budget["waiting_for_plan"] <= 0.01 + 2 * h.dt + 1e-9
    assert budget["moving_full"] + budget["moving_scaled"] > 0
    moved = next(t for t, q, _, _ in h.log if np.linalg.norm(q[:3]) > 1e-6)
    assert moved <= 0.01 + 3 * h.dt + 1e-9


def test_a_robot_at_rest_never_sets_off_before_the_gripper_has_done() -> None:
    """A plan ready early waits for the gripper's dwell (``not_before``): the robot sets off when the dwell
    ends, not when the plan is ready, and the time until then is the gripper's."""
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B", not_before=0.2)
    h.run(3.0)
    moved = next(t for t, q, _, _ in h.log if np.linalg.norm(q[:3]) > 1e-6)
    assert 0.2 - 1e-9 <= moved <= 0.2 + 2 * h.dt + 1e-9
    budget = h.sup.counters.budget_s
    assert budget["gripper"] == pytest.approx(0.2, abs=h.dt + 1e-9)
    assert budget["waiting_for_plan"] <= h.dt + 1e-9


def test_a_robot_at_rest_keeps_the_start_deadline_where_its_plan_fails_the_forecast_sooner() -> None:
    """A plan brought forward is a plan at another time: checked against the latest forecast as it would run
    from then. Where that check fails the robot does not set off early; it keeps the switch at the start
    deadline, where the plan is checked again at the timing it was planned for, and sets off then."""
    h = Harness(lambda t: person_at(FAR))
    checked: list[float] = []

    def predicted_check(traj, forecast, *, timing=None):
        checked.append(float(traj.t_start))
        return (traj.t_start if traj.t_start < 0.3 - 1e-6 else None), traj.t_end

    h.planner.predicted_check = predicted_check  # type: ignore[method-assign]
    h.sup.timing = object()  # the from-rest check is the predicted one (the fake planner ignores the timing)
    h.sup.set_goal("B")
    h.run(1.0)
    start = h.config.start_deadline
    early = [t for t in checked if t < start - 1e-6]
    assert early, "the plan was never tried before its start deadline"
    moved = next(t for t, q, _, _ in h.log if np.linalg.norm(q[:3]) > 1e-6)
    assert start - 1e-9 <= moved <= start + 2 * h.dt + 1e-9
    assert not [k for _, k, _ in h.events if k == "plan_failed"]


def test_a_missed_deadline_leaves_the_plan_until_its_violation_is_due() -> None:
    """Every backup misses D, so none is produced (the paper's rule): the robot goes on along its plan, whose
    predicted violation is still beyond T_i + D, and stops (with the emergency plan) once that violation
    comes within D, not at the first miss; the separation holds throughout."""
    h = Harness(WALK_IN, forecast_fn=perfect_forecast(WALK_IN, 0.5))
    h.sup.set_goal("B")
    h.run(0.3)  # started (the start backup met its deadline)
    h.jobs.fixed_compute_s = 0.15  # slower than D = 0.1 from now on
    h.run(2.5)
    c = h.sup.counters
    misses = [t for t, k, _ in h.events if k == "deadline_miss"]
    stops = [(t, p) for t, k, p in h.events if k == "stop_replan"]
    assert len(misses) >= 3 and c.deadline_misses == len(misses)
    assert c.online_replans == 0
    assert len(stops) == 1
    t_stop, stop = stops[0]
    assert stop["reason"] == "predicted_violation" and t_stop > misses[2]
    assert stop["violation_t"] <= t_stop + h.config.deadline_s  # stopped once its violation was due
    assert stop["scale"] > 0 and c.stop_replans_moving == 1  # under way until then
    assert c.emergency_plans >= 1
    assert _monitor_violations(h) == 0


def test_planner_exception_takes_the_emergency_path() -> None:
    h = Harness(WALK_IN, forecast_fn=perfect_forecast(WALK_IN, 0.5))
    h.planner.raise_after = 1  # the start plan works, every later one raises
    h.sup.set_goal("B")
    h.run(2.0)
    c = h.sup.counters
    assert c.stop_replans >= 1 and c.plan_failures >= 1
    assert any(k == "plan_failed" and "error" in p["reason"] for _, k, p in h.events)
    assert _monitor_violations(h) == 0


def test_stale_stream_stops_until_frames_resume() -> None:
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(0.8)
    assert h.log[-1][2] == pytest.approx(1.0)
    h.frames_on = False
    h.sup.set_stale(True, h.t)
    h.run(1.6)
    assert h.sup.status().stale
    q_stale = [q[0] for t, q, _, _ in h.log if t >= 1.3]
    assert max(q_stale) - min(q_stale) < 1e-9  # at rest while stale
    assert h.sup.counters.stale_stops == 1
    h.sup.set_stale(False, h.t)
    h.frames_on = True
    h.run(6.0)
    assert h.sup.take_arrival() == "B"
    assert h.kinds().count("stale_stream") == 1 and h.kinds().count("stream_resumed") == 1


def test_estop_holds_until_reset() -> None:
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(0.6)
    h.sup.estop(h.t, source="test")
    q_e = h.log[-1][1].copy()
    h.run(2.0)
    assert h.sup.state == "nominal" and h.sup.status().state == "estop"
    assert all(np.allclose(q, q_e) for t, q, _, _ in h.log if t > 0.6)
    h.sup.reset(h.t, q_e)
    h.sup.set_goal("B")
    h.run(8.0)
    assert h.sup.take_arrival() == "B"
    assert "estop" in h.kinds()


def test_speed_is_scaled_near_a_person_and_the_monitor_stays_clean() -> None:
    # a person standing beside the path: the robot slows down while passing, and never violates S_p
    # (0.6 m from the path: closer and no plan passes; at 0.75 m the robot keeps its full speed)
    h = Harness(lambda t: person_at(np.array([0.75, 0.6, 0.0])))
    h.sup.set_goal("B")
    h.run(8.0)
    # slowed below full speed after the ramp up (the robot starts at 0.3 s, at full speed by 0.55 s; less
    # than a robot moving straight at the person: it passes by)
    assert min(s for t, _, s, _ in h.log if t > 0.6 and s > 0) < 0.9
    assert h.sup.take_arrival() == "B"
    assert _monitor_violations(h) == 0
    # the slowing shows in the mean speed scale under way: lower than with nobody near, the same motion
    far = Harness(lambda t: person_at(FAR))
    far.sup.set_goal("B")
    far.run(8.0)
    c, c_far = h.sup.counters, far.sup.counters
    assert c.moving_time_s > c_far.moving_time_s
    assert c.scale_time_s / c.moving_time_s < c_far.scale_time_s / c_far.moving_time_s - 0.01


def test_a_robot_moving_away_from_a_person_is_not_slowed(monkeypatch: pytest.MonkeyPatch) -> None:
    """ISO/TS 15066 takes the robot's speed *toward* the person: a robot setting off straight away from a
    person 0.48 m behind it runs exactly as with nobody near, while the same motion judged by its whole
    speed (as if it moved at the person) is slowed; the monitor stays clean both ways."""
    monkeypatch.setattr(sys.modules[__name__], "CLEAR", 0.15)  # the fake planner: start 0.48 m from them

    def run(person: np.ndarray, toward: bool) -> tuple[np.ndarray, int]:
        cfg = SupervisorConfig(deadline_s=0.1, frame_period_s=1 / 30, robot_toward=toward)
        h = Harness(lambda t: person_at(person), config=cfg)
        h.run(0.5)  # the person's speed measured over a window first (before it, the fastest is assumed)
        h.sup.set_goal("B")
        h.run(6.5)
        assert h.sup.take_arrival() == "B"
        return np.array([s for _, _, s, _ in h.log]), _monitor_violations(h)

    behind = np.array([-0.58, 0.0, 0.0])  # the robot starts at the origin and moves along +x
    alone, _ = run(FAR, True)
    away, v_away = run(behind, True)
    whole, v_whole = run(behind, False)
    np.testing.assert_array_equal(away, alone)  # not slowed at all
    under_way = slice(81, 321)  # after the ramp up (the robot sets off at 0.51 s), before the arrival
    assert alone[under_way].min() == 1.0
    assert whole[under_way].min() < 0.9  # the whole-speed governor slowed it
    assert v_away == v_whole == 0


def test_the_closing_bound_holds_between_its_samples() -> None:
    """:func:`app.safety.governor.closing_bound` bounds the separation of a moving point from a fixed one at
    every instant of its path, not only at the samples: straight away it is minus the speed, straight at
    the person the speed, and past them in between."""
    from app.safety.governor import closing_bound

    rng = np.random.default_rng(3)
    person = np.array([0.0, 0.0, 0.0])
    for k in range(300):
        p0 = rng.uniform(-1.0, 1.0, 3)
        vel = rng.uniform(-1.0, 1.0, 3)
        curve = rng.uniform(-2.0, 2.0, 3) * (k % 3 == 1)  # straight, or bending
        if k % 3 == 2:  # straight away, braking to rest at the end of the window
            vel = p0 / np.linalg.norm(p0) * rng.uniform(0.2, 1.0)
            curve = -vel / (2 * 0.9)
        taus = np.arange(0.0, 0.9 + 1e-9, 0.02)

        def dist(t: np.ndarray, p0=p0, vel=vel, curve=curve) -> np.ndarray:
            pts = p0 + np.outer(t, vel) + np.outer(t**2, curve)
            return np.linalg.norm(pts - person, axis=1) - R_HUMAN

        v_lip = np.array([np.linalg.norm(vel) + 2 * np.linalg.norm(curve) * 0.9])
        c, slack = closing_bound(taus, dist(taus)[:, None], v_lip)
        fine = np.linspace(0.0, 0.9, 2001)
        assert np.all(dist(fine) >= dist(taus[:1])[0] - c[0] * fine - slack[0] - 1e-12), k
        assert slack[0] <= v_lip[0] * 0.04 + 1e-12
    speed = 0.5
    taus = np.arange(0.0, 0.9 + 1e-9, 0.02)
    away = (0.4 + speed * taus)[:, None]
    at = (0.9 - speed * taus)[:, None]
    assert closing_bound(taus, away, np.array([speed]))[0][0] == pytest.approx(-speed)
    assert closing_bound(taus, at, np.array([speed]))[0][0] == pytest.approx(speed, rel=0.05)


def test_person_rushing_at_the_robot_never_breaks_the_separation() -> None:
    """The person runs at 1.6 m/s straight at the moving robot: the governor brakes in time."""

    def person(t: float) -> np.ndarray:
        x = 3.0 - 1.6 * max(t - 0.5, 0.0)
        return person_at(np.array([max(x, 0.9), 0.0, 0.0]))

    h = Harness(person)
    h.sup.set_goal("B")
    h.run(3.0)
    assert _monitor_violations(h) == 0
    # the robot gave way: it was brought (nearly) to rest while the person came at it
    assert min(v for t, _, _, v in h.log if 1.0 <= t <= 2.0) < 0.05


def test_path_time_slows_the_timing_not_the_path() -> None:
    # the governor judging the robot by its whole speed (as if it moved straight at the person) slows it
    # past the person enough to show the mechanism
    cfg = SupervisorConfig(deadline_s=0.1, frame_period_s=1 / 30, robot_toward=False)
    near = Harness(lambda t: person_at(np.array([0.75, 0.62, 0.0])), config=cfg)
    far = Harness(lambda t: person_at(FAR), config=cfg)
    for h in (near, far):
        h.sup.set_goal("B")
        h.run(10.0)
    t_near = next(t for t, q, _, _ in near.log if q[0] >= 2.0 - 1e-9)
    t_far = next(t for t, q, _, _ in far.log if q[0] >= 2.0 - 1e-9)
    assert t_near > t_far + 0.1
    # same straight path, only slower
    assert max(abs(q[1]) for _, q, _, _ in near.log) < 1e-9
    # no jumps: per-tick motion bounded by the plan speed
    steps = [np.linalg.norm(b[1] - a[1]) for a, b in zip(near.log[:-1], near.log[1:], strict=True)]
    assert max(steps) <= SPEED * 0.01 + 1e-9


def test_lazy_jobs_compute_only_the_backups_that_are_consumed() -> None:
    h = Harness(lambda t: person_at(FAR))
    h.sup.set_goal("B")
    h.run(4.0)
    # 120 frames submitted a backup; only the start plan was ever needed
    assert h.sup.counters.frames >= 100
    assert h.planner.plan_calls == 1
    assert h.sup.counters.plans_computed == 1


def test_config_validation_and_jobs_bound() -> None:
    with pytest.raises(ValueError, match="method"):
        SupervisorConfig(method="psychic")  # type: ignore[arg-type]
    assert SupervisorConfig(deadline_s=0.1, frame_period_s=1 / 30).max_jobs == 3
    assert SupervisorConfig(deadline_s=0.2, frame_period_s=1 / 30).max_jobs == 6
    assert math.isclose(SupervisorConfig().emergency_horizon, 0.1 + 1 / 30)


def test_the_compiled_governor_equals_the_numpy_reference() -> None:
    """The servo tick's compiled target scale (separation bound, braking envelope over the moving parts,
    speed-scaling law) equals the NumPy reference, with and without a measurement of the person."""
    h = Harness(lambda t: person_at(FAR))
    sup = h.sup
    rng = np.random.default_rng(8)
    L = 7
    sup.n_parts = L
    seen = set()
    for i in range(1500):
        measured = i % 5 != 0
        sep_m = rng.uniform(-0.05, 1.2, L)
        v_h0 = rng.uniform(-0.5, 2.5, L)
        sup._v_h_t = float(rng.uniform(-0.1, 0.0)) if measured else -math.inf
        x_h0 = np.asarray(SSM.human_approach(v_h0, -sup._v_h_t if measured else 0.0)[0])
        sup._parts = PartSeparation(sep_m, x_h0, v_h0, ssm_alone(L))
        sup._travel = rng.uniform(0.0, 0.05, L)
        vmax = rng.uniform(0.0, 1.5, L) * (rng.uniform(size=L) > 0.2)
        # the closing along the path measured at the frame (a part moving away: negative), where it covers
        # the tick and the brake (or not), or none
        sup._toward = None
        if i % 3:
            sup._toward = (
                sup._active,
                PathClosing(
                    sup._tau - float(rng.uniform(0.0, 0.05)),
                    sup._tau + float(rng.choice([rng.uniform(0.0, 0.3), math.inf])),
                    rng.uniform(-1.5, 1.5, L),
                    rng.uniform(0.0, 0.02, L),
                ),
            )
        s = float(rng.uniform(0.0, 1.0))
        rate = float(rng.uniform(1.0, 20.0))
        lo, hi = max(s - rate * 0.008, 0.0), s + 0.04
        sup.speed_scale_law = None if i % 7 == 0 else LAW
        with np.errstate(invalid="ignore"):
            want = governed_scale_reference(sup, 0.0, 0.008, s, vmax, rate, lo, hi)
        got = sup._governed_scale(0.0, 0.008, s, vmax, rate, lo, hi)
        assert got == pytest.approx(want, abs=1e-12), i
        seen.add("hi" if got == pytest.approx(min(hi, 1.0)) else "zero" if got == 0.0 else "between")
    assert seen == {"hi", "zero", "between"}


class _PointCapsules:
    """The point robot as the collision model of the SSM timing (one part, a person of points)."""

    def robot_capsules(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        return q[:, None, :3].copy(), q[:, None, :3].copy(), np.zeros(1)

    def human_capsules(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        joints = np.asarray(joints, dtype=float)
        return joints.copy(), joints.copy(), np.full(joints.shape[-2], R_HUMAN)

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        return (np.linalg.norm(np.asarray(joints) - np.asarray(q)[:3], axis=-1) - R_HUMAN)[:, None, :]


@pytest.mark.parametrize("strict", [False, True])
@pytest.mark.parametrize("side_m", [0.3, 0.62, 0.75, 0.9])
def test_the_ssm_timing_predicts_how_long_the_governor_takes_past_a_person(
    side_m: float, strict: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The governor's model (app.safety.governor.GovernorModel), fed the person as they stand, predicts the
    time the supervisor's governor really takes along a straight move past them, within 20 % (the governor
    ramps up from rest at its ramp rate, picks scales from a grid and sees frames of varying age; the model
    takes the oldest)."""
    from app.planning.ssm_timing import predicted_arrival_from, predicted_scales
    from app.safety.governor import GovernorModel

    separation = SSM
    if strict:  # a person assumed to speed up faster: the governor slows the robot far more
        separation = dataclasses.replace(SSM, human_accel_mps2=30.0, human_speed_max_mps=3.0)
        monkeypatch.setattr(sys.modules[__name__], "SSM", separation)
    where = np.array([0.75, side_m, 0.0])
    h = Harness(lambda t: person_at(where))
    h.sup.set_goal("B")
    h.run(40.0)
    assert h.sup.take_arrival() == "B"
    moving = [t for t, q, _, v in h.log if v > 1e-6]
    measured = moving[-1] - moving[0]
    cfg = h.config
    model = GovernorModel(
        separation=separation,
        brake_decel_mps2=cfg.brake_decel_mps2,
        brake_joint_decel=cfg.brake_joint_decel,
        tracking_margin_m=cfg.tracking_margin_m,
        speed_window_s=cfg.human_speed_window_s,
        sensing_age_s=cfg.frame_period_s,  # frames arrive as taken: at most one frame period old
        near_band_m=cfg.near_band_m,
        lookahead_s=cfg.profile_window_s,
        law=LAW,
    )
    # the path the supervisor ran (straight, or round the person where they stand in its way)
    fc = HumanForecast.hold(HumanFrame(0.0, person_at(where)))
    plan = FakePlanner(h.goals).plan(q_start=np.zeros(6), t_start=0.0, goal="B", forecast=fc).plan
    traj = LinearTrajectory(plan.times, plan.q)
    _, t, _ = predicted_scales(traj, fc, _PointCapsules(), model)
    full = traj.t_end - traj.t_start
    print(side_m, strict, t[-1], measured, full)
    if strict and side_m < 0.8:
        assert measured > 1.5 * full  # the governor slowed this move a lot ...
    assert t[-1] == pytest.approx(measured, rel=0.2)  # ... and the prediction knew by how much
    # the rest of the move from its middle, reached at another time: the same timing (the person holds still)
    tau, _, _ = predicted_scales(traj, fc, _PointCapsules(), model)
    tau_m = 0.5 * (traj.t_start + traj.t_end)
    t_m = float(np.interp(tau_m, tau, t))
    assert predicted_arrival_from(traj, traj.t_start, traj.t_start, fc, _PointCapsules(), model) == t[-1]
    rest = predicted_arrival_from(traj, tau_m, 10.0, fc, _PointCapsules(), model) - 10.0
    assert rest == pytest.approx(t[-1] - t_m, rel=0.05, abs=0.05)


def test_the_status_says_what_limits_the_robot_and_the_separation_it_is_held_to() -> None:
    """The status's modes (:func:`app.safety.modes.part_modes`) follow the governor: free with nobody near,
    not free while the governor holds the robot below full speed, stopped at an E-stop; its separation and
    required separation are the limiting part's, and a robot at or below its limit is never closer than it."""
    # a person comes from far away to 0.45 m beside the middle of the path, and stays there
    person = walker(np.array([1.0, 3.0, 0.0]), np.array([1.0, 0.45, 0.0]), 1.0, 2.5)
    h = Harness(person, forecast_fn=lambda t: HumanForecast.hold(HumanFrame(t, person_at(FAR))))
    h.sup.set_goal("B")
    h.run(1.0)
    st = h.sup.status()
    assert [m.mode for m in st.modes] == ["free"] and st.scale == pytest.approx(1.0)
    assert st.separation_m == st.modes[0].separation_m and st.required_separation_m == st.modes[0].required_m
    assert st.required_separation_m < st.separation_m
    seen = set()
    while h.t < 4.0:
        h.run(h.t + 0.05)
        st = h.sup.status()
        (m,) = st.modes
        seen.add(m.mode)
        assert m.mode in ("free", "ssm", "stopped")  # SSM alone here: no region to touch
        if st.scale < 0.99 and st.state == "nominal" and m.mode == "free":
            assert m.limit_scale == pytest.approx(1.0)  # only ramping up
        if st.state == "nominal" and m.mode != "stopped" and st.scale <= m.limit_scale:
            # not braking down to a lower limit: the separation it is held to is kept
            assert st.required_separation_m <= st.separation_m + 1e-9
    assert "free" in seen and ({"ssm", "stopped"} & seen)
    h.sup.estop(h.t)
    assert [m.mode for m in h.sup.status().modes] == ["stopped"]


# ----------------------------------------------------------------------------------------------------------
# the reactive method's plan as a candidate of the proactive method's decisions


def _request(forecast: HumanForecast, candidate: HumanForecast | None, *, sets_off: bool = True) -> Any:
    from app.control.backup import BackupRequest

    return BackupRequest(
        key=1, t_request=0.0, t_start=0.1, q_start=np.zeros(6), qd_start=np.zeros(6), goal="B",
        forecast=forecast, deadline_s=None, candidate=candidate, sets_off=sets_off,
    )  # fmt: skip


def _walk_onto_the_path(at: float, x: float = 1.0) -> HumanForecast:
    """A forecast person far away who stands on the straight path to B (at ``x``) from ``at`` on."""
    on = person_at(np.array([x, 0.0, 0.0]))
    return HumanForecast(
        t0=0.0, times=np.array([0.0, at - 0.01, at]), joints=np.stack([person_at(FAR), person_at(FAR), on]),
        margins=np.zeros(3),
    )  # fmt: skip


def _computer(planner: FakePlanner) -> BackupComputer:
    c = BackupComputer(planner, make_traj, PointGeometry(), deadline_s=0.1, workers=1, timer=_FakeTimer())
    c.enforce_deadline = False
    return c


def test_the_reactive_plan_is_taken_where_it_arrives_earlier_under_the_forecast() -> None:
    """A search that detours where it need not (its own forecast clear of the straight path): the reactive
    method's straight plan passes the check under that forecast and arrives earlier, so it is taken, with
    the time it gains; where the straight plan would meet the forecast person, the forecast's own wins."""
    planner = FakePlanner({"B": np.array([2.0, 0.0, 0.0])})
    far = HumanForecast.hold(HumanFrame(0.0, person_at(FAR)))
    clear = dataclasses.replace(far)  # the proactive forecast: nobody near, another object than the held one
    real = planner.plan

    def cautious(**kw: Any) -> FakeResult:  # the forecast's own search goes round where it need not
        if kw["forecast"] is clear:
            a, b, side = np.asarray(kw["q_start"])[:3], planner.goals["B"], np.array([0.0, 1.0, 0.0])
            return FakeResult(True, planner._line([a, a + side, b + side, b], kw["t_start"]), "ok")
        return real(**kw)

    planner.plan = cautious  # type: ignore[method-assign]
    out = _computer(planner).compute_raw(_request(clear, far))
    assert out.status == "ok" and out.chosen == "reactive"
    straight, detour = 2.0 / SPEED, (1.0 + 2.0 + 1.0) / SPEED
    assert out.arrival_s == pytest.approx(0.1 + straight)
    assert out.gain_s == pytest.approx(detour - straight)
    assert abs(out.traj.q(0.1 + straight / 2)[1]) < 1e-9  # the straight plan
    # the straight plan would meet the forecast person on the path: the forecast's own (the detour) is kept
    out = _computer(planner).compute_raw(_request(_walk_onto_the_path(1.5), far))
    assert out.status == "ok" and out.chosen == "forecast" and out.gain_s == 0.0
    assert out.traj.q(2.5)[1] == pytest.approx(1.0)  # on the detour


@pytest.mark.parametrize("sets_off", [True, False])
def test_where_the_forecast_finds_no_plan_a_clear_reactive_one_is_taken(sets_off: bool) -> None:
    """The forecast's own search finds no plan (more cautious than the check). The reactive method's
    straight plan is taken where it passes the check under the forecast, from rest or under way; where the
    forecast person would meet it (on the path from 1.5 s on, long after the switch's T_i + D), it is not:
    the supervisor would have to stop it for them."""
    planner = FakePlanner({"B": np.array([2.0, 0.0, 0.0])})
    far = HumanForecast.hold(HumanFrame(0.0, person_at(FAR)))
    real = planner.plan

    def blocked(**kw: Any) -> FakeResult:  # the forecast's own search: the goal looks occupied
        if kw["forecast"] is not far:
            return FakeResult(False, None, "goal blocked (test)", blocked="goal")
        return real(**kw)

    planner.plan = blocked  # type: ignore[method-assign]
    clear = dataclasses.replace(far)
    out = _computer(planner).compute_raw(_request(clear, far, sets_off=sets_off))
    assert out.status == "ok" and out.chosen == "reactive_only" and out.gain_s == 0.0
    out = _computer(planner).compute_raw(_request(_walk_onto_the_path(1.5), far, sets_off=sets_off))
    assert out.status == "failed" and out.chosen is None and out.blocked == "goal"


def test_the_reactive_method_weighs_no_candidate() -> None:
    """The reactive method's forecast is the held pose itself: one plan per request, nothing counted."""
    planner = FakePlanner({"B": np.array([2.0, 0.0, 0.0])})
    far = HumanForecast.hold(HumanFrame(0.0, person_at(FAR)))
    out = _computer(planner).compute_raw(_request(far, far))
    assert out.status == "ok" and out.chosen is None and planner.plan_calls == 1


def test_a_robot_at_rest_sets_off_on_the_reactive_plan_instead_of_waiting() -> None:
    """The forecast's own search finds no plan for the first 2 s (it holds the goal for occupied), though
    the straight path is clear of the forecast person. Without the candidate the robot at rest waits; with
    it, it sets off at once on the reactive method's plan, and arrives."""
    arrivals = {}
    for candidate in (False, True):
        h = Harness(lambda t: person_at(FAR), candidate=candidate)
        real = h.planner.plan

        def cautious(real: Any = real, h: Harness = h, **kw: Any) -> FakeResult:
            if h.t < 2.0 and kw["forecast"].times.size > 1:  # the forecast's own search, not the held pose's
                return FakeResult(False, None, "goal blocked (test)", blocked="goal")
            return real(**kw)

        h.planner.plan = cautious  # type: ignore[method-assign]
        h.forecast_fn = lambda t: HumanForecast(
            t0=t, times=np.array([t, t + 1.0]), joints=np.stack([person_at(FAR)] * 2), margins=np.zeros(2)
        )
        h.sup.set_goal("B")
        h.run(3.0)
        moving = [t for t, _, _, v in h.log if v > 1e-6]
        arrivals[candidate] = moving[0] if moving else math.inf
        if candidate:
            assert h.sup.counters.plan_choices["reactive_only"] >= 1
            assert h.sup.counters.budget_s["waiting_for_person"] == 0.0
        else:
            assert h.sup.counters.budget_s["waiting_for_person"] > 1.5
        assert _monitor_violations(h) == 0
    assert arrivals[False] > 2.0  # waited until its own search found a plan
    assert arrivals[True] < 0.5


@pytest.mark.parametrize("governed", [False, True])
def test_a_plan_setting_off_is_rechecked_at_the_timing_it_was_verified_at(governed: bool) -> None:
    """The forecast has a person stand on the straight path (x = 1 m) from 4 s to 6 s: the plan at its own
    (predicted) timing is past them by 3.5 s; timed at half speed it would meet them. With the
    governor's model the supervisor re-checks the plan that sets the robot off as the planner verified it
    (here the fake planner's own timing) and sets off on it; without, at half speed, it refuses it and
    waits for the person to pass (or goes round)."""
    on = person_at(np.array([1.0, 0.0, 0.0]))

    def fc(t: float) -> HumanForecast:
        times = np.array([t, 4.0 - 0.01, 4.0, 6.0, 6.0 + 0.01]) if t < 4.0 - 0.01 else np.array([t, t + 5])
        if times.size == 2:
            return HumanForecast.hold(HumanFrame(t, person_at(FAR)))
        joints = np.stack([person_at(FAR), person_at(FAR), on, on, person_at(FAR)])
        return HumanForecast(t0=t, times=times, joints=joints, margins=np.zeros(5))

    h = Harness(lambda t: person_at(FAR), forecast_fn=fc, timing=object() if governed else None)
    h.sup.set_goal("B")
    h.run(1.0)
    rejected = [t for t, k, p in h.events if k == "plan_failed" and "violates the latest" in p["reason"]]
    moving = [q for _, q, _, v in h.log if v > 1e-6]
    if governed:
        assert not rejected and moving and abs(moving[0][1]) < 1e-9  # straight at once
    else:
        assert rejected  # timed at half speed, the straight plan meets the crossing person


def test_a_robot_held_still_by_a_person_may_take_another_goal_and_one_under_way_may_not() -> None:
    """:meth:`Supervisor.still_for` counts how long the person has held the robot still with a goal; a
    held robot takes another goal from where it stands (the plans for the old one are void) and gets there;
    a robot under way keeps its goal (:meth:`Supervisor.reroute` refuses and changes nothing)."""
    goals = {"B": np.array([2.0, 0.0, 0.0]), "C": np.array([0.0, -2.0, 0.0])}
    free = Harness(lambda t: person_at(FAR), goals=goals)
    free.sup.set_goal("B")
    free.run(0.5)
    assert free.log[-1][2] > 0.5 and free.sup.still_for(free.t) < 0.05  # under way (since the last tick)
    assert not free.sup.reroute("C", free.t)
    assert free.sup.goal == "B"
    assert "rerouted" not in free.kinds()

    # a person standing on the way to B, whom the forecast misses: the governor holds the robot short of them
    h = Harness(lambda t: person_at([1.0, 0.0, 0.0]), goals=goals,
                forecast_fn=lambda t: HumanForecast.hold(HumanFrame(t, person_at(FAR))))  # fmt: skip
    h.sup.set_goal("B")
    h.run(3.0)
    assert h.sup.take_arrival() is None
    assert h.sup.still_for(h.t) > 1.0
    x_held = h.log[-1][1][0]
    assert h.sup.reroute("C", h.t)
    assert h.sup.goal == "C" and h.sup.still_for(h.t) == 0.0
    assert [p for _, k, p in h.events if k == "rerouted"] == [{"goal": "C"}]
    # (it crept on: it stops first, a stop & replan, and sets off for C from rest)
    assert [p["reason"] for _, k, p in h.events if k == "stop_replan"] == ["rerouted"]
    h.run(h.t + 8.0)
    assert h.sup.take_arrival() == "C"
    np.testing.assert_allclose(h.log[-1][1][:3], goals["C"], atol=1e-9)
    assert h.log[-1][1][0] == pytest.approx(0.0) and x_held > 0.0
    assert _monitor_violations(h) == 0
